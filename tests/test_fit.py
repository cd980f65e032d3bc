"""The fit stage and its pieces: Gaussian model, PLY, strategies, training loop, checkpoints, NaN guard.

The sfm stage's output is built here from a synthetic scene's KNOWN cameras and points sampled on its
true geometry (:func:`sgpor_pipeline.stages.fit.write_known_sfm`): the "known cameras" input of the
fit stage, so these tests do not depend on SfM.
"""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
import torch

from sgpor_pipeline.dag import RunInputs, Stage, StageContext
from sgpor_pipeline.errors import NonFiniteError, PipelineError
from sgpor_pipeline.gaussians import strategy as S
from sgpor_pipeline.gaussians.model import GaussianModel, rgb_to_sh
from sgpor_pipeline.gaussians.ply import property_names, read_ply, write_ply
from sgpor_pipeline.gaussians.rasterizer import cpu_kernel_available
from sgpor_pipeline.gaussians.train import (
    BudgetController,
    TrainParams,
    _ssim_kernel_applies,
    _SSIMMean,
    _SSIMMeanKernel,
    photometric_loss,
    resolve_device,
    ssim_map,
    ssim_mean,
)
from sgpor_pipeline.runner import run_pipeline
from sgpor_pipeline.stages.fit import FitParams, FitStage, fit_scene, write_known_sfm
from sgpor_pipeline.synthetic import SceneParams, generate_scene

TESTS = Path(__file__).resolve().parent
LOG = logging.getLogger("sgpor_pipeline.fit")

# Small and fast: a 16-view inward rig at 96x72 (views 0 and 8 held out); a fit of a few hundred
# iterations takes seconds.
SMALL = SceneParams(seed=3, n_views=16, width=96, height=72, n_background_objects=4)


@pytest.fixture(scope="module")
def small_scene():
    return generate_scene(SMALL)


def make_sfm(folder: Path, scene, n_points: int = 1500, seed: int = 0) -> Path:
    return write_known_sfm(folder, scene.cameras, scene.images, scene.depth,
                           [scene.background_mesh, scene.object_mesh], n_points=n_points, seed=seed)


def quick_params(**kw) -> FitParams:
    base = dict(iterations=150, eval_every=0, checkpoint_every=0, checkpoint_seconds=0, n_renders=1,
                holdout_every=8, sh_degree=1, sh_degree_every=50)
    base.update(kw)
    return FitParams(**base)


def all_finite(path: Path) -> bool:
    model = read_ply(path)
    return all(bool(torch.isfinite(p).all()) for p in model.params.values())


# --------------------------------------------------------------------------------------------------
# model, PLY


def random_model(n: int, degree: int, seed: int = 0) -> GaussianModel:
    g = torch.Generator().manual_seed(seed)
    model = GaussianModel.empty(n, degree)
    for p in model.params.values():
        p.data = torch.randn(p.shape, generator=g)
    return model


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_ply_round_trip_is_exact(tmp_path, degree):
    model = random_model(37, degree, seed=degree)
    path = write_ply(tmp_path / "g.ply", model)
    back = read_ply(path)
    assert back.max_sh_degree == degree and len(back) == 37
    for name, p in model.params.items():
        assert torch.equal(p.detach(), back.params[name].detach()), name
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    props = [line.split()[-1] for line in header.splitlines() if line.startswith("property")]
    assert props == property_names(degree)
    assert "binary_little_endian" in header and all("property float " in x for x in header.splitlines()
                                                     if x.startswith("property"))
    # channel-major f_rest: f_rest_0..K-2 are the red coefficients
    k1 = (degree + 1) ** 2 - 1
    if k1:
        raw = np.frombuffer(path.read_bytes()[len(header) + len("end_header\n"):], "<f4").reshape(37, -1)
        first_rest = props.index("f_rest_0")
        assert np.array_equal(raw[:, first_rest:first_rest + k1], model.params["shN"].detach().numpy()[:, :, 0])


@pytest.mark.parametrize("degree", [0, 3])
def test_an_empty_model_round_trips(tmp_path, degree):
    """e.g. the remove stage's object.ply when nothing was deleted"""
    from sgpor_pipeline.removal.holes import subset

    empty = subset(random_model(5, degree), np.zeros(5, bool))
    back = read_ply(write_ply(tmp_path / "empty.ply", empty))
    assert len(back) == 0 and back.max_sh_degree == degree


def test_ply_is_read_by_open3d(tmp_path):
    o3d = pytest.importorskip("open3d")
    model = random_model(11, 3)
    path = write_ply(tmp_path / "g.ply", model)
    pc = o3d.t.io.read_point_cloud(str(path))
    names = set(pc.point)
    assert {"positions", "f_dc", "f_rest", "opacity", "scale", "rot"} <= names
    p = {n: t.detach().numpy() for n, t in model.params.items()}
    assert np.array_equal(pc.point["positions"].numpy(), p["means"])
    assert np.array_equal(pc.point["f_dc"].numpy(), p["sh0"][:, 0])
    assert np.array_equal(pc.point["f_rest"].numpy(), p["shN"])  # Open3D reads f_rest as [N, K-1, 3]
    assert np.array_equal(pc.point["opacity"].numpy()[:, 0], p["opacities"])
    assert np.array_equal(pc.point["rot"].numpy(), p["quats"])
    assert np.allclose(pc.point["scale"].numpy(), np.exp(p["scales"]), rtol=1e-6)  # Open3D activates scales


def test_ply_refuses_non_finite(tmp_path):
    model = random_model(4, 0)
    model.params["means"].data[1, 2] = float("nan")
    with pytest.raises(Exception, match="NaN"):
        write_ply(tmp_path / "g.ply", model)
    assert not (tmp_path / "g.ply").exists()


def test_init_from_points_colours_and_scales():
    xyz = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [5, 5, 5]], float)
    rgb = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [128, 128, 128], [0, 0, 0]], np.uint8)
    m = GaussianModel.from_points(xyz, rgb, 2, scene_extent=10.0)
    assert len(m) == 5 and m.params["shN"].shape == (5, 8, 3)
    assert torch.allclose(m.colors_dc(), torch.from_numpy(rgb / 255.0).float(), atol=1e-6)
    s = m.scales_linear()
    assert torch.all(s <= 1.0 + 1e-6) and torch.all(s > 0)  # clamped to 0.1 x extent
    assert torch.allclose(m.opacities_activated(), torch.full((5,), 0.1), atol=1e-6)
    assert torch.allclose(rgb_to_sh(torch.tensor([0.5])), torch.tensor([0.0]))
    act, geometry = m.activated(), m.activated(sh=False)
    assert act["colors"].shape == (5, 9, 3) and "colors" not in geometry
    assert all(torch.equal(act[k], geometry[k]) for k in ("means", "quats", "scales", "opacities"))


# --------------------------------------------------------------------------------------------------
# loss


def test_ssim_map_equals_kornia():
    kornia = pytest.importorskip("kornia")
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1, 3, 40, 52, generator=g)
    y = (x + 0.1 * torch.randn(1, 3, 40, 52, generator=g)).clamp(0, 1)
    assert torch.allclose(ssim_map(x, y), kornia.metrics.ssim(x, y, 11), atol=2e-5)
    img = torch.rand(30, 20, 3, generator=g)
    assert float(photometric_loss(img, img, 0.2)) < 1e-5


def test_weighted_loss_ignores_zero_weight_pixels_and_has_exact_gradients():
    """Per-pixel weights (finetune's observed/unobserved pixels): pixels of weight 0 change neither the
    loss nor get a gradient; weight 1 everywhere equals the plain loss; the analytic SSIM backward
    with weights matches autograd through the SSIM map (float64)."""
    g = torch.Generator().manual_seed(1)
    x = torch.rand(24, 28, 3, generator=g, dtype=torch.float64)
    y = torch.rand(24, 28, 3, generator=g, dtype=torch.float64)
    w = torch.zeros(24, 28, dtype=torch.float64)
    w[:, :14] = 1.0
    ones = torch.ones(24, 28, dtype=torch.float64)
    assert torch.allclose(photometric_loss(x, y, 0.2, ones), photometric_loss(x, y, 0.2))
    y2 = y.clone()
    y2[:, 20:] = 0.5  # farther than the SSIM window (5 px) from any weighted pixel
    assert torch.allclose(photometric_loss(x, y, 0.2, w), photometric_loss(x, y2, 0.2, w))
    xr = x.clone().requires_grad_(True)
    photometric_loss(xr, y, 0.2, w).backward()
    assert float(xr.grad[:, 20:].abs().max()) == 0.0 and float(xr.grad[:, :14].abs().min()) > 0
    wr = torch.rand(24, 28, generator=g, dtype=torch.float64)
    a = x.permute(2, 0, 1).clone().requires_grad_(True)
    ssim_mean(a, y.permute(2, 0, 1), wr).backward()
    b = x.permute(2, 0, 1).clone().requires_grad_(True)
    m = ssim_map(b[None], y.permute(2, 0, 1)[None])[0]
    ((m * wr).sum() / (wr.sum() * 3)).backward()
    assert torch.allclose(a.grad, b.grad, atol=1e-10)


needs_kernel = pytest.mark.skipif(not cpu_kernel_available(), reason="the cpu kernel is not built")


@needs_kernel
@pytest.mark.parametrize("dtype, tol", [(torch.float32, 2e-6), (torch.float64, 1e-13)])
@pytest.mark.parametrize("hw", [(6, 6), (13, 40), (48, 64)])
@pytest.mark.parametrize("weighted", [False, True])
def test_fused_ssim_matches_the_torch_ssim(dtype, tol, hw, weighted):
    """The kernel's fused SSIM (csrc/ssim.h) gives the torch version's value and gradient to rounding,
    from the smallest image reflect padding allows (6 x 6) up, plain and weighted."""
    g = torch.Generator().manual_seed(hw[0] * 100 + hw[1])
    x = torch.rand(3, *hw, generator=g, dtype=dtype)
    y = (x + 0.2 * torch.randn(3, *hw, generator=g, dtype=dtype)).clamp(0, 1)
    w = (torch.rand(*hw, generator=g) * (torch.rand(*hw, generator=g) > 0.3)).to(dtype) if weighted else None
    xa, xb = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
    a, b = _SSIMMean.apply(xa, y, w), _SSIMMeanKernel.apply(xb, y, w)
    assert a.dtype == b.dtype == dtype and b.shape == ()
    assert abs(float(a.detach()) - float(b.detach())) < tol
    a.backward()
    b.backward()
    assert xb.grad.shape == x.shape and xb.grad.dtype == dtype
    assert float((xa.grad - xb.grad).abs().max()) <= tol * float(xa.grad.abs().max()) * 10


@needs_kernel
@pytest.mark.parametrize("weighted", [False, True])
def test_fused_ssim_gradcheck(weighted):
    g = torch.Generator().manual_seed(3)
    x = torch.rand(2, 7, 9, generator=g, dtype=torch.float64, requires_grad=True)
    y = torch.rand(2, 7, 9, generator=g, dtype=torch.float64)
    w = torch.rand(7, 9, generator=g, dtype=torch.float64) if weighted else None
    assert torch.autograd.gradcheck(lambda t: _SSIMMeanKernel.apply(t, y, w), (x,), eps=1e-6, atol=1e-8)


@needs_kernel
def test_fused_ssim_does_not_depend_on_the_thread_count(monkeypatch):
    g = torch.Generator().manual_seed(4)
    x = torch.rand(3, 37, 50, generator=g, requires_grad=True)
    y = torch.rand(3, 37, 50, generator=g)
    w = torch.rand(37, 50, generator=g)
    results = []
    for threads in ("1", "3"):
        monkeypatch.setenv("SGPOR_NUM_THREADS", threads)
        x.grad = None
        v = _SSIMMeanKernel.apply(x, y, w)
        v.backward()
        results.append((float(v.detach()), x.grad.clone()))
    assert results[0][0] == results[1][0] and torch.equal(results[0][1], results[1][1])


def test_ssim_mean_takes_the_kernel_only_where_it_applies():
    x32, x64 = torch.rand(3, 8, 8), torch.rand(3, 8, 8, dtype=torch.float64)
    assert _ssim_kernel_applies(x32, x32) == cpu_kernel_available()
    assert not _ssim_kernel_applies(x32, x64)  # mixed dtypes: the torch version
    assert not _ssim_kernel_applies(x32.half(), x32.half())
    # both paths give the loss the trainer uses, the kernel's where it applies
    assert abs(float(ssim_mean(x32, x32)) - 1.0) < 1e-5


# --------------------------------------------------------------------------------------------------
# strategies: the Adam moments follow every change of the Gaussian set


def optimizers_for(model: GaussianModel) -> dict:
    opts = {n: torch.optim.Adam([p], lr=1e-3, eps=1e-15) for n, p in model.params.items()}
    for n, p in model.params.items():
        p.grad = torch.ones_like(p)
        opts[n].step()
        opts[n].zero_grad()
    return opts


def check_aligned(model: GaussianModel, opts: dict) -> None:
    for n, p in model.params.items():
        assert opts[n].param_groups[0]["params"][0] is p
        st = opts[n].state[p]
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape


def test_duplicate_split_remove_keep_moments_aligned():
    model = random_model(10, 1)
    opts = optimizers_for(model)
    gen = torch.Generator().manual_seed(0)
    mask = torch.zeros(10, dtype=torch.bool)
    mask[[1, 4]] = True
    S.duplicate(model, opts, mask)
    assert len(model) == 12
    check_aligned(model, opts)
    assert torch.equal(model.params["means"][10:], model.params["means"][[1, 4]])
    assert float(opts["means"].state[model.params["means"]]["exp_avg"][10:].abs().sum()) == 0
    mask = torch.zeros(12, dtype=torch.bool)
    mask[0] = True
    before = model.scales_linear()[0].clone()
    S.split(model, opts, mask, gen)
    assert len(model) == 13
    check_aligned(model, opts)
    assert torch.allclose(model.scales_linear()[-1], before / 1.6)
    keep = torch.ones(13, dtype=torch.bool)
    keep[:3] = False
    S.remove(model, opts, keep)
    assert len(model) == 3
    check_aligned(model, opts)


def test_adc_respects_the_budget():
    model = random_model(50, 0)
    model.params["opacities"].data.fill_(2.0)
    model.params["scales"].data.fill_(math.log(0.05))
    opts = optimizers_for(model)
    strat = S.ADCStrategy(cap=60, iterations=1000)
    state = strat.initialize_state(model, 1.0)
    state["grad2d"] += 1.0
    state["count"] += 1.0
    out = strat._refine(model, opts, state, torch.Generator().manual_seed(0))
    assert len(model) == 60 and out["cloned"] + out["split"] == 10
    check_aligned(model, opts)


def test_mcmc_relocation_and_growth():
    model = random_model(100, 1)
    model.params["opacities"].data.fill_(0.0)
    model.params["opacities"].data[:10] = -20.0  # dead
    opts = optimizers_for(model)
    strat = S.MCMCStrategy(cap=120, iterations=1000, params=S.MCMCParams(grow_rate=1.05))
    gen = torch.Generator().manual_seed(0)
    n = strat._relocate(model, opts, gen)
    assert n == 10 and bool((model.opacities_activated() > strat.p.min_opacity).all())
    added = strat._add(model, opts, gen)
    assert added == 5 and len(model) == 105
    for _ in range(10):
        strat._add(model, opts, gen)
    assert len(model) == 120  # the cap
    check_aligned(model, opts)
    # relocation formula: one Gaussian split into n copies keeps its opacity composite 1-(1-o)^n = o
    op = torch.tensor([0.6, 0.6])
    new_op, new_scales = strat._relocation(op, torch.ones(2, 3), torch.tensor([1, 3]))
    assert torch.allclose(new_op[0], op[0]) and torch.allclose(new_scales[0], torch.ones(3))
    assert torch.allclose(1 - (1 - new_op[1]) ** 3, op[1])
    assert bool(torch.isfinite(new_scales).all())


def test_budget_controller_grows_then_freezes():
    p = TrainParams(budget=None, budget_per_pixel=0.01, budget_min=100, budget_window=10, budget_min_gain=0.05)
    b = BudgetController.create(p, 20_000)
    assert b.auto and b.cap == 200
    assert not b.due(5, 100, True)  # below the cap: no decision
    assert b.due(5, 200, True) and b.decide(5, 200, 1.0, "held-out MSE") and b.cap == 300  # first: grow
    assert not b.due(10, 300, True)  # within the window
    assert not b.due(20, 300, False)  # densification over
    assert b.due(20, 300, True) and b.decide(20, 300, 0.5, "held-out MSE") and b.cap == 450  # fell 50 %
    assert b.due(40, 450, True) and not b.decide(40, 450, 0.49, "held-out MSE") and b.frozen  # fell 2 %
    assert "frozen at 450" in b.reason and "held-out MSE" in b.reason
    assert not b.due(100, 450, True)
    fixed = BudgetController.create(replace(p, budget=1234), 20_000)
    assert not fixed.auto and fixed.cap == 1234 and not fixed.due(100, 1234, True)


# --------------------------------------------------------------------------------------------------
# the fit


def test_fit_reaches_psnr_on_a_small_scene(tmp_path, small_scene):
    """Bound: the mean-colour baseline (every held-out pixel predicted as the mean training colour)
    scores 16.1 dB on this scene; 400 iterations at 96x72 from 1500 true-geometry points topped up to
    4000 (depth-interpolated) reached 21.3 dB held-out (SSIM 0.56) in our runs (the default 256x192
    scene reaches 30 dB with 2000 iterations, see benchmarks/fit.py). We require 19.5 dB AND 3.5 dB
    over the baseline (no constant image gets there; a fit that learns the scene does, with margin)
    and SSIM > 0.45."""
    sfm = make_sfm(tmp_path / "sfm", small_scene)
    out = tmp_path / "fit"
    out.mkdir()
    res = fit_scene(sfm, out, quick_params(iterations=400, eval_every=200, sh_degree=0, init_points=4000), None,
                    LOG)
    assert res["heldout_views"] == ["view_000", "view_008"]
    assert res["heldout_psnr"] >= 19.5, res
    assert res["heldout_psnr"] >= res["mean_color_baseline_psnr"] + 3.5, res
    assert res["heldout_ssim"] > 0.45
    for name in ("gaussians.ply", "curve.json", "curve.png", "fit.json"):
        assert (out / name).is_file(), name
    assert len(list((out / "renders").glob("*.png"))) == 1
    curve = json.loads((out / "curve.json").read_text())["curve"]
    assert [c["iteration"] for c in curve][-1] == 400
    assert {"iteration", "loss", "count", "seconds", "heldout_psnr", "heldout_ssim"} <= set(curve[-1])
    assert curve[-1]["loss"] < curve[0]["loss"]
    fit = json.loads((out / "fit.json").read_text())
    for key in ("count", "stop_reason", "heldout_psnr", "heldout_ssim", "seconds", "iterations", "scene_extent",
                "training_resolution"):
        assert key in fit, key
    assert fit["training_resolution"] == [96, 72] and all_finite(out / "gaussians.ply")
    assert fit["points"]["points_added"] == 2500 and fit["points"]["init_mode"] == "depth"  # 1500 + 2500


def test_fit_resolution_and_budget_params(tmp_path, small_scene):
    sfm = make_sfm(tmp_path / "sfm", small_scene, n_points=400)
    out = tmp_path / "fit"
    out.mkdir()
    res = fit_scene(sfm, out, quick_params(iterations=120, max_size=32, budget=450, holdout_every=0), None, LOG)
    assert res["training_resolution"] == [32, 24]
    assert "points_added" not in res["points"]  # 400 SfM points > the automatic init count at 32x24
    assert res["count"] <= 450 and res["budget"] == 450 and not res["budget_auto"]
    assert res["heldout_is_training"] and res["heldout_views"] == []
    assert math.isfinite(res["heldout_psnr"])


def test_a_coarse_phase_trains_on_downscaled_views_then_on_full_ones(tmp_path, small_scene, monkeypatch):
    """``fit.coarse_until``: the first half of the iterations renders each view at half its size, its
    intrinsics scaled with it and its image the area average of the full one; the rest, the held-out
    scoring and the renders are at full size. The fit still learns the scene (the bound of
    test_fit_reaches_psnr_on_a_small_scene)."""
    import cv2

    from sgpor_pipeline.gaussians import train as train_mod

    seen: list[tuple[int, int, float, float]] = []
    real = train_mod.rasterization

    def spy(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **kw):
        seen.append((width, height, float(Ks[0, 0, 0]), float(Ks[0, 0, 2])))
        return real(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **kw)

    monkeypatch.setattr(train_mod, "rasterization", spy)
    sfm = make_sfm(tmp_path / "sfm", small_scene)
    out = tmp_path / "fit"
    out.mkdir()
    res = fit_scene(sfm, out, quick_params(iterations=400, sh_degree=0, init_points=4000, coarse_until=0.5),
                    None, LOG)
    full = small_scene.cameras[1].K
    assert {s[:2] for s in seen[:200]} == {(48, 36)} and {s[:2] for s in seen[200:400]} == {(96, 72)}
    assert seen[0][2:] == pytest.approx((full[0, 0] / 2, full[0, 2] / 2), rel=1e-6)
    assert seen[399][2:] == pytest.approx((full[0, 0], full[0, 2]), rel=1e-6)
    assert all(s[:2] == (96, 72) for s in seen[400:]) and len(seen) > 400  # scoring and renders
    assert res["training_resolution"] == [96, 72]
    assert res["heldout_psnr"] >= 19.5 and res["heldout_psnr"] >= res["mean_color_baseline_psnr"] + 3.5, res

    with pytest.raises(PipelineError, match="coarse_until"):
        fit_scene(sfm, tmp_path / "bad", quick_params(coarse_until=1.5), None, LOG)

    # the coarse view is the area average of the full one
    view = train_mod.make_view("v", small_scene.images[1], small_scene.cameras[1])
    model = GaussianModel.empty(0, 0)
    trainer = train_mod.Trainer(model, S.ADCStrategy(1000, 10), [view], [],
                                TrainParams(iterations=10, coarse_until=0.5), extent=1.0)
    small, _ = trainer._view(0, 5)
    expect = cv2.resize(view.image.numpy(), (48, 36), interpolation=cv2.INTER_AREA)
    assert np.abs(small.image.numpy() - expect).max() < 1e-5
    assert trainer._view(0, 6)[0] is view and not trainer._coarse


def test_nan_guard_rolls_back_and_lowers_the_lr(tmp_path, small_scene, caplog):
    sfm = make_sfm(tmp_path / "sfm", small_scene, n_points=500)
    out = tmp_path / "fit"
    out.mkdir()
    with caplog.at_level(logging.WARNING, logger="sgpor_pipeline.fit"):
        res = fit_scene(sfm, out, quick_params(iterations=120, debug_inject_nan_at=70), None, LOG)
    assert len(res["rollbacks"]) == 1
    rb = res["rollbacks"][0]
    assert rb["iteration"] == 70 and rb["to_iteration"] == 50 and rb["lr_scale"] == 0.5
    assert "means" in rb["what"]
    assert res["lr_scale"] == 0.5 and res["iterations"] == 120
    assert any("non-finite parameter 'means'" in r.getMessage() and "rolled back" in r.getMessage()
               for r in caplog.records)
    assert all_finite(out / "gaussians.ply") and math.isfinite(res["heldout_psnr"])
    # A NaN that comes back every time: give up with NonFiniteError after max_rollbacks, write nothing.
    out2 = tmp_path / "fit2"
    out2.mkdir()
    with pytest.raises(NonFiniteError, match="means"):
        fit_scene(sfm, out2, quick_params(iterations=120, debug_inject_nan_at=70, debug_inject_nan_times=100),
                  None, LOG)
    assert not (out2 / "gaussians.ply").exists()


def test_a_non_finite_loss_rolls_back(tmp_path, small_scene, monkeypatch, caplog):
    # The loss is checked together with the gradients (one GPU synchronisation): a NaN loss at one
    # iteration still rolls back, named as the loss (not as the gradients it poisoned).
    from sgpor_pipeline.gaussians import train as T

    sfm = make_sfm(tmp_path / "sfm", small_scene, n_points=500)
    out = tmp_path / "fit"
    out.mkdir()
    real, calls = T.photometric_loss, []

    def nan_once(*args, **kwargs):
        calls.append(1)
        loss = real(*args, **kwargs)
        return loss * float("nan") if len(calls) == 60 else loss

    monkeypatch.setattr(T, "photometric_loss", nan_once)
    with caplog.at_level(logging.WARNING, logger="sgpor_pipeline.fit"):
        res = fit_scene(sfm, out, quick_params(iterations=100), None, LOG)
    assert [(rb["iteration"], rb["what"]) for rb in res["rollbacks"]] == [(60, "non-finite loss")]
    assert any("non-finite loss at iteration 60" in r.getMessage() for r in caplog.records)
    assert res["iterations"] == 100 and all_finite(out / "gaussians.ply")


def test_the_rasterizer_scans_only_parameters_the_trainer_has_not_checked(tmp_path, small_scene, monkeypatch):
    # The trainer checks every parameter after each step, so the next rasterization skips its own
    # scan of them (check_finite=False); the first iteration and the one after a rollback scan. The
    # activations can still make one non-finite input from finite parameters: exp(log-scale) overflows
    # to inf. Unscanned, the kernel culls such a Gaussian (as one with a NaN centre): the step goes on.
    from sgpor_pipeline.gaussians import train as T

    sfm = make_sfm(tmp_path / "sfm", small_scene, n_points=500)
    out = tmp_path / "fit"
    out.mkdir()
    real_raster, real_loss, checks, losses = T.rasterization, T.photometric_loss, [], []

    def spy(means, quats, scales, *args, **kwargs):
        if "check_finite" not in kwargs:  # (the renders after training)
            return real_raster(means, quats, scales, *args, **kwargs)
        checks.append(kwargs["check_finite"])
        if len(checks) == 20:
            means, scales = means.clone(), scales.clone()
            scales[0] = float("inf")
            means[1, 0] = float("nan")
        return real_raster(means, quats, scales, *args, **kwargs)

    def nan_at_40(*args, **kwargs):
        losses.append(1)
        loss = real_loss(*args, **kwargs)
        return loss * float("nan") if len(losses) == 40 else loss

    monkeypatch.setattr(T, "rasterization", spy)
    monkeypatch.setattr(T, "photometric_loss", nan_at_40)
    res = fit_scene(sfm, out, quick_params(iterations=60), None, LOG)
    assert [(rb["iteration"], rb["what"]) for rb in res["rollbacks"]] == [(40, "non-finite loss")]
    assert [i + 1 for i, c in enumerate(checks) if c] == [1, 41]
    assert res["iterations"] == 60 and all_finite(out / "gaussians.ply")


def test_after_the_step_only_parameters_changed_since_adam_are_scanned(tmp_path, small_scene, monkeypatch):
    # Adam keeps finite parameters finite when their gradients are (those are scanned before it), so
    # after it the trainer scans only the parameters something else changed: all of them on the first
    # iteration and when densification replaced them, the one the debug injection wrote into in place,
    # none on an ordinary iteration. A strategy's NaN written in place is still caught by name.
    from sgpor_pipeline.gaussians import train as T

    sfm = make_sfm(tmp_path / "sfm", small_scene, n_points=500)
    names = {"means", "quats", "scales", "opacities", "sh0", "shN"}
    real, scans = T.first_non_finite, []

    def spy(tensors):
        if "loss" not in tensors and set(tensors) <= names:  # (the scan after the step)
            scans.append(set(tensors))
        return real(tensors)

    monkeypatch.setattr(T, "first_non_finite", spy)
    out = tmp_path / "fit"
    out.mkdir()
    res = fit_scene(sfm, out, quick_params(iterations=220, densify_until=1.0, debug_inject_nan_at=170), None, LOG)
    assert [(rb["iteration"], rb["to_iteration"]) for rb in res["rollbacks"]] == [(170, 150)]
    events = json.loads((out / "curve.json").read_text())["events"]
    densified = {e["iteration"] for e in events if e["event"] == "adc"}
    assert densified == {200}
    iterations = list(range(1, 171)) + list(range(151, 221))  # (rolled back at 170 to 150)
    assert len(scans) == len(iterations)
    for k, it in enumerate(iterations):
        first = k in (0, 170)  # the first iteration, and the first after the rollback
        want = names if first or it in densified else {"means"} if k == 169 else set()
        assert scans[k] == want, (k, it, scans[k])

    # a NaN that the strategy writes in place (not a new tensor) is caught and named
    real_post = S.ADCStrategy.step_post_backward

    def poisoning(self, model, optimizers, state, step, info, lr=0.0):
        changed = real_post(self, model, optimizers, state, step, info, lr)
        if step == 30 and not getattr(self, "poisoned", False):
            self.poisoned = True
            with torch.no_grad():
                model.params["opacities"][3] = float("nan")
        return changed

    monkeypatch.setattr(S.ADCStrategy, "step_post_backward", poisoning)
    out2 = tmp_path / "fit2"
    out2.mkdir()
    res = fit_scene(sfm, out2, quick_params(iterations=60), None, LOG)
    assert [(rb["iteration"], rb["what"]) for rb in res["rollbacks"]] == [(30, "non-finite parameter 'opacities'")]
    assert res["iterations"] == 60 and all_finite(out2 / "gaussians.ply")


def test_hard_cases_stay_finite(tmp_path, small_scene):
    # (a) only 20 SfM points
    sfm = make_sfm(tmp_path / "sfm20", small_scene, n_points=20)
    out = tmp_path / "fit20"
    out.mkdir()
    res = fit_scene(sfm, out, quick_params(iterations=120, max_size=48), None, LOG)
    # The 20 points are all used; the fit tops the initialisation up to its init_points (points_added).
    assert res["points"]["points_in"] == 20 and res["points"]["used"] == 20 + res["points"].get("points_added", 0)
    assert math.isfinite(res["heldout_psnr"]) and all_finite(out / "gaussians.ply")

    # (b) some points absurdly far away (1e4 x the scene extent), and a view of constant colour
    sfm = make_sfm(tmp_path / "sfmfar", small_scene, n_points=300)
    pts = dict(np.load(sfm / "points.npz"))
    ext = 2.0
    far = np.random.default_rng(0).normal(size=(10, 3))
    far = far / np.linalg.norm(far, axis=1, keepdims=True) * 1e4 * ext
    pts["xyz"] = np.concatenate([pts["xyz"], far])
    pts["rgb"] = np.concatenate([pts["rgb"], np.full((10, 3), 200, np.uint8)])
    np.savez(sfm / "points.npz", **pts)
    from sgpor_pipeline.imageio import write_png

    write_png(sfm / "images" / "view_001.png", np.full((48, 64, 3), 77, np.uint8))
    out = tmp_path / "fitfar"
    out.mkdir()
    res = fit_scene(sfm, out, quick_params(iterations=120, max_size=48), None, LOG)
    assert res["points"]["points_far"] == 10
    assert math.isfinite(res["heldout_psnr"]) and all_finite(out / "gaussians.ply")

    # (c) the far points kept (no filter): still finite
    out = tmp_path / "fitfar_kept"
    out.mkdir()
    res = fit_scene(sfm, out, quick_params(iterations=120, max_size=48, far_points=0.0), None, LOG)
    assert res["points"]["points_in"] == 310 and res["points"]["points_far"] == 0
    assert res["points"]["used"] == 310 + res["points"].get("points_added", 0) and all_finite(out / "gaussians.ply")


def test_drop_masked_points_drops_what_most_observers_see_inside_a_mask():
    from sgpor_pipeline.gaussians.train import make_view
    from sgpor_pipeline.stages.fit import SfmPoints, drop_masked_points

    scene = generate_scene(SceneParams(seed=0, n_views=4, width=48, height=36))
    views = [make_view(c.name, img, c, 0, ~m) for c, img, m in zip(scene.cameras, scene.images, scene.masks)]
    on_object = np.asarray(scene.object_mesh.sample_points_uniformly(200).points)
    lo, hi = scene.object_bounds
    background = np.asarray(scene.background_mesh.sample_points_uniformly(2000).points)
    background = background[~((background > lo - 0.3) & (background < hi + 0.3)).all(1)][:300]
    xyz = np.concatenate([on_object, background])
    pts = SfmPoints(xyz, np.zeros((len(xyz), 3), np.uint8))
    kept, dropped = drop_masked_points(pts, views, {c.name: i for i, c in enumerate(scene.cameras)})
    assert dropped >= 0.8 * len(on_object) and len(kept.xyz) == len(xyz) - dropped
    assert np.isin(background, kept.xyz).all(1).sum() >= 0.95 * len(background)  # the background stays
    # observations follow the kept points; a view without a weight map changes nothing
    n = len(xyz)
    obs_point, obs_view = np.arange(n).repeat(4), np.tile(np.arange(4), n)
    kept2, dropped2 = drop_masked_points(SfmPoints(xyz, None, obs_point, obs_view), views,
                                         {c.name: i for i, c in enumerate(scene.cameras)})
    assert dropped2 == dropped and len(kept2.obs_point) == 4 * len(kept2.xyz) and kept2.obs_point.max() < len(kept2.xyz)
    unweighted = [make_view(c.name, img, c) for c, img in zip(scene.cameras, scene.images)]
    assert drop_masked_points(pts, unweighted, {})[1] == 0


def test_fit_can_leave_the_given_masks_out(tmp_path, small_scene):
    """``fit.object_masks = "ignore"``: the pixels inside the given masks are not supervised, so the
    fit models the background alone: inside the masks its renders do not show the object (they are
    farther from the photos than the ordinary fit's and closer to the object-free truth), the SfM
    points on the object are dropped, and a view without a mask is refused with a clear error."""
    from sgpor_pipeline.errors import PipelineError
    from sgpor_pipeline.gaussians.train import render_view
    from sgpor_pipeline.imageio import write_mask01

    sfm = make_sfm(tmp_path / "sfm", small_scene)
    (sfm / "masks").mkdir()
    for name, mask in zip(small_scene.names, small_scene.masks):
        write_mask01(sfm / "masks" / f"{name}.png", mask)
    errors = {}
    for mode in ("fit", "ignore"):
        out = tmp_path / mode
        out.mkdir()
        res = fit_scene(sfm, out, quick_params(iterations=300, sh_degree=0, holdout_every=0, init_points=3000,
                                               object_masks=mode), None, LOG)
        assert res["object_masks"] == mode
        model = read_ply(out / "gaussians.ply")
        to_photo, to_truth = [], []
        for cam, photo, truth, mask in zip(small_scene.cameras, small_scene.images, small_scene.images_gt,
                                           small_scene.masks):
            with torch.no_grad():
                img = render_view(model, cam, 0).clamp(0, 1).numpy()
            to_photo.append(np.abs(img - photo)[mask].mean())
            to_truth.append(np.abs(img - truth)[mask].mean())
        errors[mode] = (float(np.mean(to_photo)), float(np.mean(to_truth)), res["points"].get("points_masked", 0))
    assert errors["fit"][2] == 0 and errors["ignore"][2] > 0, errors
    assert errors["ignore"][0] > 1.5 * errors["fit"][0], errors  # the object is not reproduced ...
    assert errors["ignore"][1] < errors["ignore"][0], errors  # ... the background behind it is
    out = tmp_path / "auto"
    out.mkdir()
    assert fit_scene(sfm, out, quick_params(iterations=10, object_masks="auto"), None, LOG)["object_masks"] == "ignore"
    (sfm / "masks" / "view_003.png").unlink()
    with pytest.raises(PipelineError, match="view_003"):
        fit_scene(sfm, tmp_path / "ignore", quick_params(iterations=10, object_masks="ignore"), None, LOG)
    # "auto" fits the object when a view has no mask
    res = fit_scene(sfm, out, quick_params(iterations=10, object_masks="auto"), None, LOG)
    assert res["object_masks"] == "fit" and "points_masked" not in res["points"]


def test_mcmc_strategy_fits(tmp_path, small_scene):
    sfm = make_sfm(tmp_path / "sfm", small_scene, n_points=500)
    out = tmp_path / "fit"
    out.mkdir()
    # 400 iterations: refinements run at 200 and 300 (after refine_start, before 0.8 x iterations).
    res = fit_scene(sfm, out, quick_params(iterations=400, strategy="mcmc", budget=800, sh_degree=0), None, LOG)
    assert 500 < res["count"] <= 800 and all_finite(out / "gaussians.ply")
    assert res["heldout_psnr"] > res["mean_color_baseline_psnr"] + 1.0  # measured +1.9 dB


# --------------------------------------------------------------------------------------------------
# the training device


def test_resolve_device():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto", backend="cpu") == torch.device("cpu")  # our kernel runs on the CPU only
    if not torch.cuda.is_available():
        assert resolve_device("auto") == torch.device("cpu")
        with pytest.raises(ValueError, match="no CUDA device"):
            resolve_device("cuda")
    for bad in ("tpu", "gpu", "meta"):
        with pytest.raises(ValueError, match="'auto', 'cpu' or 'cuda"):
            resolve_device(bad)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error on a machine without CUDA")
def test_fit_on_a_missing_gpu_fails_before_any_work(tmp_path, small_scene):
    from sgpor_pipeline.errors import PipelineError

    sfm = make_sfm(tmp_path / "sfm", small_scene, n_points=300)
    out = tmp_path / "fit"
    out.mkdir()
    with pytest.raises(PipelineError, match="fit.device") as e:
        fit_scene(sfm, out, quick_params(device="cuda"), None, LOG)
    assert "fit.device=cpu" in e.value.fix
    assert not any(out.iterdir())


def check_cuda_fit_matches_cpu(sfm: Path, tmp: Path, strategy: str) -> dict:
    """The same fit on the CPU and on CUDA (gsplat when installed, else the torch reference there):
    both learn the scene, and agree to within what their rasterizers' rounding and alpha clamps
    (0.99 ours, 0.999 gsplat) explain; then the CUDA fit resumes from its checkpoint. Returns the
    results (the GPU check script prints them)."""
    def params(**kw) -> FitParams:
        return quick_params(sh_degree=1, init_points=4000, strategy=strategy, checkpoint_every=150,
                            budget=6000 if strategy == "mcmc" else None, **kw)

    res = {}
    for dev in ("cpu", "cuda"):
        out = tmp / f"fit_{strategy}_{dev}"
        out.mkdir(parents=True)
        res[dev] = fit_scene(sfm, out, params(iterations=400, eval_every=200, device=dev), out / "ckpt", LOG)
        assert all_finite(out / "gaussians.ply")
    cpu, gpu = res["cpu"], res["cuda"]
    assert cpu["device"] == "cpu" and gpu["device"].startswith("cuda")
    for r in (cpu, gpu):
        assert r["heldout_psnr"] >= r["mean_color_baseline_psnr"] + 3.0, r
    assert abs(gpu["heldout_psnr"] - cpu["heldout_psnr"]) < 1.0, (gpu["heldout_psnr"], cpu["heldout_psnr"])
    assert abs(gpu["count"] - cpu["count"]) <= 0.2 * cpu["count"], (gpu["count"], cpu["count"])
    # resume on CUDA from the CPU-side checkpoint file of iteration 300 (read onto the CPU, then moved)
    out = tmp / f"fit_{strategy}_cuda"
    res["resumed"] = fit_scene(sfm, out, params(iterations=450, eval_every=0, device="cuda"), out / "ckpt", LOG)
    assert res["resumed"]["resumed_from_iteration"] == 300 and res["resumed"]["iterations"] == 450
    assert res["resumed"]["heldout_psnr"] > gpu["mean_color_baseline_psnr"] + 3.0
    return res


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("strategy", ["adc", "mcmc"])
def test_fit_on_cuda_matches_the_cpu_fit(tmp_path, small_scene, strategy):
    check_cuda_fit_matches_cpu(make_sfm(tmp_path / "sfm", small_scene), tmp_path, strategy)


# --------------------------------------------------------------------------------------------------
# the stage in the pipeline: checkpoints and resume after SIGKILL


@dataclass
class KnownSfmParams:
    seed: int = 3
    n_views: int = 12
    width: int = 64
    height: int = 48
    n_points: int = 800


class KnownSfm(Stage):
    """A test stand-in for the sfm stage: known cameras and true-geometry points of a synthetic scene."""

    name = "sfm"
    Params = KnownSfmParams

    def run(self, ctx: StageContext) -> None:
        p = ctx.params
        scene = generate_scene(SceneParams(seed=p.seed, n_views=p.n_views, width=p.width, height=p.height,
                                           n_background_objects=4))
        make_sfm(ctx.out_dir, scene, n_points=p.n_points)


STAGES = {"sfm": KnownSfm, "fit": FitStage}
RESUME_OVERRIDES = ["fit.iterations=400", "fit.checkpoint_every=40", "fit.checkpoint_seconds=0",
                    "fit.eval_every=200", "fit.sh_degree=0", "fit.holdout_every=4"]

CHILD = """
import sys
sys.path.insert(0, {tests!r})
from pathlib import Path
from test_fit import STAGES, RESUME_OVERRIDES
from sgpor_pipeline.dag import RunInputs
from sgpor_pipeline.runner import run_pipeline
run_pipeline(Path({out!r}), RunInputs(images=Path({images!r})), overrides=RESUME_OVERRIDES, until="fit",
             stages=STAGES)
"""


def test_killed_fit_resumes_from_its_checkpoint(tmp_path):
    images = tmp_path / "images"
    images.mkdir()
    out = tmp_path / "out"
    script = CHILD.format(tests=str(TESTS), out=str(out), images=str(images))
    env = dict(os.environ, TQDM_DISABLE="1", OMP_WAIT_POLICY="PASSIVE")
    proc = subprocess.Popen([sys.executable, "-c", script], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT)
    ckpt = None
    try:
        deadline = time.time() + 120
        while time.time() < deadline and proc.poll() is None:
            found = list((out / "cache" / "fit").glob(".tmp-*/_checkpoint/fit_checkpoint.pt")) \
                if (out / "cache" / "fit").is_dir() else []
            if found:
                ckpt = found[0]
                st = torch.load(ckpt, weights_only=False)
                if st["step"] >= 80:  # at least two checkpoints written: kill mid-fit
                    break
            time.sleep(0.2)
        assert proc.poll() is None, "the fit finished before it could be killed: " + proc.stdout.read().decode()
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert ckpt is not None
    saved = torch.load(next((out / "cache" / "fit").glob(".tmp-*/_checkpoint/fit_checkpoint.pt")),
                       weights_only=False)["step"]
    assert 80 <= saved < 400 and saved % 40 == 0

    result = run_pipeline(out, RunInputs(images=images), overrides=RESUME_OVERRIDES, until="fit", stages=STAGES)
    assert result.outcomes["sfm"].hit and not result.outcomes["fit"].hit
    folder = result.path("fit")
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest["resumed_from_checkpoint"] is True
    assert manifest["notes"]["resumed_from_iteration"] == saved
    curve = json.loads((folder / "curve.json").read_text())
    its = [c["iteration"] for c in curve["curve"]]
    assert curve["resumed_from_iteration"] == saved
    assert its == sorted(its) and len(set(its)) == len(its) and its[-1] == 400
    # The curve before the checkpoint is kept and continues after it.
    assert any(i <= saved for i in its) and any(i > saved for i in its)
    assert not (folder / "_checkpoint").exists()  # checkpoints never reach the published result
    assert all_finite(folder / "gaussians.ply")
    # A finished fit is a cache hit.
    again = run_pipeline(out, RunInputs(images=images), overrides=RESUME_OVERRIDES, until="fit", stages=STAGES)
    assert again.outcomes["fit"].hit


def test_evaluation_scores_a_weighted_view_where_it_was_trained(monkeypatch):
    """With fit.object_masks=ignore the views' loss weights leave the object out: the reported PSNR and
    SSIM are over the weighted pixels (the masked ones, which the fit never saw, would drag them down)."""
    from sgpor_pipeline.gaussians import train
    from sgpor_pipeline.scene import Camera

    rng = np.random.default_rng(0)
    image = torch.from_numpy(rng.random((40, 48, 3)).astype(np.float32))
    render = image + 0.05
    render[10:30, 12:36] = 0.0  # where the object was: the render shows something else
    weight = torch.ones(40, 48)
    weight[10:30, 12:36] = 0.0
    monkeypatch.setattr(train, "render_view", lambda *a, **k: render.clone())
    cam = Camera("v", 48, 40, np.array([[40.0, 0, 24], [0, 40.0, 20], [0, 0, 1]]), np.eye(4))
    plain = train.evaluate(None, [train.TrainView("v", image, cam)])
    masked = train.evaluate(None, [train.TrainView("v", image, cam, weight)])
    keep = weight.numpy() > 0
    expected = -10 * np.log10(float(((render.clamp(0, 1) - image) ** 2).numpy()[keep].mean()))
    assert masked["psnr"] == pytest.approx(expected, abs=1e-4) and masked["psnr"] > plain["psnr"] + 5
    assert masked["ssim"] > plain["ssim"]
    assert math.isnan(train.evaluate(None, [train.TrainView("v", image, cam, torch.zeros(40, 48))])["psnr"])


def test_mask_band_weights_the_background_around_the_object(tmp_path):
    """fit.mask_band_gain: with the masks left out, the photo's pixels within mask_band_rel x sqrt(mask
    area) of the (dilated) mask weigh the gain, those inside 0, the rest 1; a view without a mask pixel,
    and gain 1, keep the plain weights. Bad values are refused before the fit."""
    from sgpor_pipeline.imageio import write_mask01, write_png
    from sgpor_pipeline.scene import Camera, save_cameras
    from sgpor_pipeline.stages.fit import load_sfm_views

    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    cams = [Camera(f"v{i}", 64, 48, K, np.eye(4), image=f"v{i}") for i in range(2)]
    save_cameras(tmp_path / "cameras.json", cams)
    (tmp_path / "images").mkdir()
    (tmp_path / "masks").mkdir()
    mask = np.zeros((48, 64), bool)
    mask[20:30, 28:38] = True  # 100 px: the band is 0.5 x 10 = 5 px wide
    for i, m in enumerate((mask, np.zeros_like(mask))):
        write_png(tmp_path / "images" / f"v{i}.png", np.full((48, 64, 3), 128, np.uint8))
        write_mask01(tmp_path / "masks" / f"v{i}.png", m)
    plain, _ = load_sfm_views(tmp_path, 0, mask_dilate=0)
    views, _ = load_sfm_views(tmp_path, 0, mask_dilate=0, band_gain=3.0, band_rel=0.5)
    w, w0 = views[0].weight.numpy(), plain[0].weight.numpy()
    assert np.all(w[mask] == 0) and np.array_equal(w0, (~mask).astype(np.float32))
    assert w[25, 40] == 3.0 and w[25, 42] == 3.0 and w[25, 45] == 1.0 and w[14, 33] == 1.0
    band = (w == 3.0)
    assert band.sum() > 0 and not (band & mask).any()
    assert np.array_equal(views[1].weight.numpy(), np.ones((48, 64), np.float32))
    with pytest.raises(PipelineError, match="mask_band_gain must be >= 0"):
        fit_scene(tmp_path, tmp_path / "out", FitParams(mask_band_gain=-1.0), None, logging.getLogger("test"))


def test_a_fit_that_sees_each_photo_too_few_times_names_the_iterations_that_would():
    from sgpor_pipeline.stages.fit import MIN_PASSES_PER_VIEW, few_passes_warning

    assert MIN_PASSES_PER_VIEW == 40
    assert few_passes_warning(2000, 24) is None and few_passes_warning(2000, 50) is None  # (the demo, lund)
    assert few_passes_warning(10, 0) is None
    many = few_passes_warning(2000, 96)
    assert "2000 iterations over 96 training photos see each about 21 times" in many
    # (3840 rounded up to 500s; densification still ends at iteration 1200)
    assert "--set fit.iterations=4000 --set fit.densify_until=0.30 sees each 40 times" in many
    assert "fit.iterations=2500 --set fit.densify_until=0.48 " in few_passes_warning(2000, 51)
    assert "fit.densify_until=0.25 " in few_passes_warning(2000, 96, densify_until=0.5)
