"""The finetune stage's training device: the CPU by default here, CUDA where a GPU is (finetune.device).

Self-contained (no Open3D): a textured plane of Gaussians, a hole in the middle, four cameras."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from sgpor_pipeline.dag import StageContext
from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.gaussians.model import GaussianModel, rgb_to_sh
from sgpor_pipeline.gaussians.ply import read_ply, write_ply
from sgpor_pipeline.gaussians.train import render_view
from sgpor_pipeline.imageio import read_mask, read_rgb8, write_labels, write_mask01, write_png
from sgpor_pipeline.scene import Camera, load_cameras, save_cameras
from sgpor_pipeline.stages.finetune import FinetuneParams, FinetuneStage


def plane_inputs(root: Path, side: int = 30, w: int = 64, h: int = 48, seed: int = 0,
                 hole_box: tuple[float, float] = (1 / 3, 2 / 3), seed_extent: float = 0.35) -> dict[str, Path]:
    """The remove and refine folders of a plane scene: Gaussians on z = 2 with random colours, the
    ones in the middle (``seed_extent``) marked as hole seeds (grey), the fills a smooth colour ramp
    in the holes (the image's box from ``hole_box[0]`` to ``hole_box[1]`` of each side)."""
    rng = np.random.default_rng(seed)
    g = np.linspace(-1.2, 1.2, side)
    X, Y = np.meshgrid(g, g)
    xyz = np.stack([X.ravel(), Y.ravel(), np.full(X.size, 2.0)], axis=1)
    model = GaussianModel.empty(len(xyz), 0)
    seeds = np.flatnonzero(np.abs(xyz[:, :2]).max(axis=1) < seed_extent)
    rgb = rng.random((len(xyz), 3))
    rgb[seeds] = 0.5
    with torch.no_grad():
        model.params["means"].copy_(torch.from_numpy(xyz).float())
        model.params["scales"].fill_(float(np.log(2.4 / side)))
        model.params["opacities"].fill_(2.0)
        model.params["sh0"].copy_(rgb_to_sh(torch.from_numpy(rgb).float())[:, None, :])
    K = np.array([[w * 0.8, 0, w / 2], [0, w * 0.8, h / 2], [0, 0, 1.0]])
    cams = []
    for i, (dx, dy) in enumerate(((0.0, 0.0), (0.15, 0.0), (-0.1, 0.1), (0.05, -0.12))):
        T = np.eye(4)
        T[:2, 3] = (-dx, -dy)
        cams.append(Camera(f"v{i}", w, h, K, T, image=f"v{i}"))
    remove, refine = root / "remove", root / "refine"
    for sub in (remove / "holes", refine / "images"):
        sub.mkdir(parents=True)
    write_ply(remove / "gaussians.ply", model)
    np.save(remove / "seed_ids.npy", seeds)
    save_cameras(remove / "cameras.json", cams)
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    fill = np.stack([0.2 + 0.6 * xx, 0.3 + 0.5 * yy, 0.6 - 0.3 * xx], -1).astype(np.float32)
    for cam in cams:
        hole = np.zeros((h, w), bool)
        (y0, y1), (x0, x1) = ([int(n * f + 1e-9) for f in hole_box] for n in (h, w))  # (1/3: n // 3)
        hole[y0:y1, x0:x1] = True
        write_mask01(remove / "holes" / f"{cam.image}.png", hole)
        img = render_view(model, cam, backend="torch").numpy()
        write_png(refine / "images" / f"{cam.image}.png", np.where(hole[..., None], fill, img))
    return {"remove": remove, "refine": refine}


def run_finetune(root: Path, inputs: dict[str, Path], **kw) -> tuple[dict, GaussianModel, Path]:
    ctx = StageContext.standalone(root, "finetune", FinetuneParams(**{"iterations": 60, "max_size": 0, **kw}), inputs)
    FinetuneStage().run(ctx)
    return json.loads((ctx.out_dir / "finetune.json").read_text()), read_ply(ctx.out_dir / "gaussians.ply"), \
        ctx.out_dir


def changed(before: GaussianModel, after: GaussianModel) -> np.ndarray:
    """[N] bool: the Gaussians with any parameter value different after the re-fit."""
    return np.any([(before.params[n] != after.params[n]).reshape(len(before), -1).any(1).numpy()
                   for n in before.params], 0)


def untouched(before: GaussianModel, after: GaussianModel, trained: np.ndarray) -> bool:
    """Every Gaussian outside ``trained`` keeps its values bit for bit."""
    keep = torch.from_numpy(~trained)
    return all(torch.equal(before.params[n][keep], after.params[n][keep]) for n in before.params)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error on a machine without CUDA")
def test_finetune_on_a_missing_gpu_fails_before_any_work(tmp_path):
    inputs = plane_inputs(tmp_path / "in")
    ctx = StageContext.standalone(tmp_path, "finetune", FinetuneParams(device="cuda"), inputs)
    with pytest.raises(PipelineError, match="finetune.device") as e:
        FinetuneStage().run(ctx)
    assert "finetune.device=cpu" in e.value.fix
    assert not any(ctx.out_dir.iterdir())
    with pytest.raises(PipelineError, match="finetune.device"):
        FinetuneStage().run(StageContext.standalone(tmp_path, "finetune", FinetuneParams(device="tpu"), inputs))


def test_finetune_trains_the_hole_on_the_cpu_by_default(tmp_path):
    """Without a GPU ("auto" resolves to the CPU; with one, to it only where gsplat is installed): the
    hole's Gaussians move towards the fill, the others keep their values bit for bit."""
    inputs = plane_inputs(tmp_path / "in")
    before = read_ply(inputs["remove"] / "gaussians.ply")
    info, after, _ = run_finetune(tmp_path, inputs, device="cpu")
    assert info["device"] == "cpu" and info["iterations"] == 60
    trained = changed(before, after)
    assert 0 < trained.sum() <= info["trainable"]
    assert untouched(before, after, trained)
    seeds = np.load(inputs["remove"] / "seed_ids.npy")
    assert trained[seeds].mean() > 0.9  # the grey seeds learnt the fill


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_finetune_on_cuda_matches_the_cpu(tmp_path):
    """The same re-fit on CUDA (gsplat when installed, else the torch reference there): it trains the
    same Gaussians, leaves all others bit for bit, writes its PLY and renders from the CPU, and its
    renders agree with the CPU re-fit's to within the backends' rounding and alpha clamps."""
    inputs = plane_inputs(tmp_path / "in")
    before = read_ply(inputs["remove"] / "gaussians.ply")
    cpu, m_cpu, d_cpu = run_finetune(tmp_path / "cpu", inputs, device="cpu")
    gpu, m_gpu, d_gpu = run_finetune(tmp_path / "gpu", inputs, device="cuda")
    assert gpu["device"].startswith("cuda") and cpu["device"] == "cpu"
    assert gpu["trainable"] == cpu["trainable"] > 0
    trained_cpu, trained_gpu = changed(before, m_cpu), changed(before, m_gpu)
    assert trained_gpu.sum() <= gpu["trainable"] and (trained_gpu & trained_cpu).sum() > 0.9 * trained_cpu.sum()
    assert abs(gpu["train_psnr"] - cpu["train_psnr"]) < 0.5
    for name in ("v0", "v2"):
        a = read_rgb8(d_cpu / "renders" / f"{name}.png").astype(np.float64) / 255
        b = read_rgb8(d_gpu / "renders" / f"{name}.png").astype(np.float64) / 255
        assert -10 * np.log10(((a - b) ** 2).mean() + 1e-12) > 30.0, name


def test_focus_strategy_keeps_frozen_gaussians_through_a_rollback(tmp_path):
    """The focus mask zeroes the frozen Gaussians' gradients in place after accumulation; a NaN
    rollback replaces the parameter tensors, and the new ones get the hook too: after a rollback the
    frozen Gaussians still keep their values bit for bit, and the trainable ones learn."""
    import logging

    from sgpor_pipeline.gaussians.train import Trainer, TrainParams, make_view, scene_extent
    from sgpor_pipeline.scene import load_cameras
    from sgpor_pipeline.stages.finetune import FocusStrategy

    inputs = plane_inputs(tmp_path / "in")
    before = read_ply(inputs["remove"] / "gaussians.ply")
    model = read_ply(inputs["remove"] / "gaussians.ply")
    cams = load_cameras(inputs["remove"] / "cameras.json")
    views = [make_view(c.image, read_rgb8(inputs["refine"] / "images" / f"{c.image}.png"), c) for c in cams]
    trainable = np.zeros(len(model), bool)
    trainable[np.load(inputs["remove"] / "seed_ids.npy")] = True
    trainable[0] = True  # the Gaussian the injected NaN lands on
    tp = TrainParams(iterations=30, sh_degree=0, sh_degree_every=0, eval_every=0, checkpoint_every=0,
                     budget=len(model), debug_inject_nan_at=10)
    trainer = Trainer(model, FocusStrategy(torch.from_numpy(trainable)), views, [], tp, scene_extent(cams),
                      logger=logging.getLogger("test"))
    summary = trainer.train()
    assert [rb["iteration"] for rb in summary["rollbacks"]] == [10]
    after = trainer.model
    assert untouched(before, after, trainable)
    assert changed(before, after)[trainable].mean() > 0.9


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA device"))])
def test_finetune_refits_the_pixels_the_inpaint_stage_relit(tmp_path, device):
    """``refine/relit/<view>.png`` (inpaint.lift_shadow: a contact shadow lifted outside the holes):
    the Gaussians seen there are trained too, towards the relit colours; without it they keep their
    values bit for bit. On the CPU and, where there is one, on CUDA."""
    inputs = plane_inputs(tmp_path / "in")
    before = read_ply(inputs["remove"] / "gaussians.ply")
    cams = load_cameras(inputs["remove"] / "cameras.json")
    _, plain, _ = run_finetune(tmp_path / "plain", inputs, iterations=200, device=device)
    (inputs["refine"] / "relit").mkdir()
    for cam in cams:
        img = read_rgb8(inputs["refine"] / "images" / f"{cam.image}.png").astype(np.float32) / 255
        relit = np.zeros(img.shape[:2], bool)
        relit[2:12, 2:20] = True  # a corner far from the hole
        img[relit] = np.clip(img[relit] * 1.4, 0, 1)
        write_png(inputs["refine"] / "images" / f"{cam.image}.png", img)
        write_mask01(inputs["refine"] / "relit" / f"{cam.image}.png", relit)
    info, after, out = run_finetune(tmp_path / "relit", inputs, iterations=200, device=device)  # (Adam wanders first)
    assert info["device"].startswith(device)
    corner = render_view(before, cams[0], backend="torch").numpy()[2:12, 2:20]
    now = read_rgb8(out / "renders" / f"{cams[0].image}.png")[2:12, 2:20] / 255
    assert now.mean() > corner.mean() + 0.05  # brighter, towards the relit target
    moved, moved_plain = changed(before, after), changed(before, plain)
    assert moved.sum() > moved_plain.sum()
    xyz = before.params["means"].detach().numpy()
    uv, _ = cams[0].project(xyz)
    in_corner = (uv[:, 0] > 4) & (uv[:, 0] < 18) & (uv[:, 1] > 4) & (uv[:, 1] < 10)
    assert moved[in_corner].mean() > 0.9 and not moved_plain[in_corner].any()


def test_finetune_densifies_only_the_trainable_gaussians(tmp_path):
    """finetune.densify_budget: ADC clones and splits among the trainable Gaussians, up to the budget;
    every other Gaussian is still there with its values bit for bit (only its index may shift)."""
    from sgpor_pipeline.stages.finetune import trainable_gaussians

    inputs = plane_inputs(tmp_path / "in")
    before = read_ply(inputs["remove"] / "gaussians.ply")
    cams = [c for c in load_cameras(inputs["remove"] / "cameras.json") if c.image is not None]
    holes = [read_mask(inputs["remove"] / "holes" / f"{c.image}.png") for c in cams]  # (as the stage reads them)
    params = FinetuneParams(iterations=100, max_size=0, densify_budget=0.5, densify_grad2d=1e-9, device="cpu")
    trainable = trainable_gaussians(before, np.load(inputs["remove"] / "seed_ids.npy"), cams, holes, params)
    info, after, _ = run_finetune(tmp_path / "dense", inputs, iterations=100, densify_budget=0.5,
                                  densify_grad2d=1e-9, device="cpu")
    assert info["trainable"] == trainable.sum()
    added = len(after) - len(before)
    assert added == info["densify"]["net_added"] > 0
    assert added <= info["densify"]["budget"] == int(np.ceil(0.5 * trainable.sum()))
    assert info["densify"]["trainable_after"] == trainable.sum() + added  # (nothing is transparent here)
    assert "crop" not in info  # (ADC's thresholds are in units of the image's size: whole views)

    def rows(model: GaussianModel) -> np.ndarray:
        return np.concatenate([model.params[n].detach().reshape(len(model), -1).numpy()
                               for n in sorted(model.params)], 1)

    frozen = {r.tobytes() for r in rows(before)[~trainable]}
    assert len(frozen) == (~trainable).sum()
    assert frozen <= {r.tobytes() for r in rows(after)}
    plain, plain_model, _ = run_finetune(tmp_path / "plain", inputs, iterations=100, device="cpu")
    assert len(plain_model) == len(before) and "densify" not in plain


def test_the_trainer_steps_adam_on_the_trained_tail_only(tmp_path):
    """With the trainable Gaussians last (the finetune orders them so), the trainer steps Adam on the
    rows from the first of them (aligned down to 16 rows) only, with the same bits as the full step;
    with them scattered it takes the full step."""
    import logging

    from sgpor_pipeline.gaussians.train import Trainer, TrainParams, make_view, scene_extent
    from sgpor_pipeline.removal.holes import subset
    from sgpor_pipeline.stages.finetune import FocusStrategy

    inputs = plane_inputs(tmp_path / "in")
    cams = load_cameras(inputs["remove"] / "cameras.json")
    views = [make_view(c.image, read_rgb8(inputs["refine"] / "images" / f"{c.image}.png"), c) for c in cams]
    base = read_ply(inputs["remove"] / "gaussians.ply")
    trainable = np.zeros(len(base), bool)
    trainable[np.load(inputs["remove"] / "seed_ids.npy")] = True
    order = np.argsort(trainable, kind="stable")

    def train(model, mask, full):
        tp = TrainParams(iterations=20, sh_degree=0, sh_degree_every=0, eval_every=0, checkpoint_every=0,
                         budget=len(model))
        trainer = Trainer(model, FocusStrategy(torch.from_numpy(mask)), views, [], tp, scene_extent(cams),
                          logger=logging.getLogger("test"))
        if full:
            real = trainer._trained_tail
            trainer._trained_tail = lambda: (real()[0], None)
        trainer.train(resume=False)
        return trainer

    tail = train(subset(base, order), trainable[order], full=False)
    start = tail._grad_mask[3]
    first = int(np.flatnonzero(trainable[order])[0])
    assert start is not None and start % 16 == 0 and first - 16 < start <= first
    full = train(subset(base, order), trainable[order], full=True)
    for n in base.params:
        assert torch.equal(tail.model.params[n], full.model.params[n]), n
        st_tail = tail.optimizers[n].state.get(tail.model.params[n], {})
        st_full = full.optimizers[n].state.get(full.model.params[n], {})
        assert st_tail.keys() == st_full.keys(), n  # (none for shN: degree 0 gives it no gradient)
        assert all(torch.equal(st_tail[k], st_full[k]) for k in st_tail), n
    restored = subset(tail.model, np.argsort(order))
    assert untouched(base, restored, trainable) and changed(base, restored)[trainable].mean() > 0.9
    scattered = train(read_ply(inputs["remove"] / "gaussians.ply"), trainable, full=False)
    assert scattered._grad_mask[3] is None  # (the seeds are not the last Gaussians here)


@pytest.mark.parametrize("weighted", [False, True, "lowpass"])
def test_a_cropped_view_gives_the_whole_views_gradients(tmp_path, weighted):
    """The finetune's crop (``crop_views``): the loss of the crop around the trainable Gaussians'
    reach, scaled by its ``loss_scale``, has the gradients of the whole view's loss, the D-SSIM
    windows included, once the margin covers them (10 px); without a margin they differ at the
    crop's border. A view they do not reach is left out. With a low-pass term (``hole_detail``) on
    the reached pixels its weight counts in the crop's share too."""
    from sgpor_pipeline.gaussians.rasterizer import rasterization
    from sgpor_pipeline.gaussians.train import make_view, view_loss
    from sgpor_pipeline.removal.holes import subset
    from sgpor_pipeline.stages.finetune import crop_views, reach

    inputs = plane_inputs(tmp_path / "in", w=96, h=72)
    cam = load_cameras(inputs["remove"] / "cameras.json")[1]
    model = read_ply(inputs["remove"] / "gaussians.ply")
    trainable = np.zeros(len(model), bool)
    trainable[np.load(inputs["remove"] / "seed_ids.npy")] = True
    rng = np.random.default_rng(3)
    weight = rng.random((cam.height, cam.width)).astype(np.float32) if weighted else None
    r = reach(subset(model, trainable), cam, "auto")
    assert 0 < r.mean() < 0.5
    lowpass = None
    if weighted == "lowpass":  # (the low-pass pixels: the middle of the reach, where the weight is 0)
        lowpass = np.zeros(r.shape, np.float32)
        ys, xs = np.nonzero(r)
        lowpass[(ys.min() + ys.max()) // 2 - 4:(ys.min() + ys.max()) // 2 + 4,
                (xs.min() + xs.max()) // 2 - 4:(xs.min() + xs.max()) // 2 + 4] = 1.0
        weight = np.where(lowpass > 0, 0.0, weight).astype(np.float32)
    view = make_view(cam.image, rng.random((cam.height, cam.width, 3)).astype(np.float32), cam, 0, weight,
                     lowpass=lowpass, lowpass_sigma=1.5)

    def grads(v):
        p = {n: t.detach().clone().requires_grad_(True) for n, t in model.params.items()}
        vm, K = v.viewmat, v.K
        img, _, _ = rasterization(p["means"], p["quats"], torch.exp(p["scales"]), torch.sigmoid(p["opacities"]),
                                  p["sh0"], vm, K, v.camera.width, v.camera.height, sh_degree=0,
                                  backgrounds=torch.zeros(3), grad_mask=torch.from_numpy(trainable))
        (view_loss(img[0], v, 0.2) * v.loss_scale).backward()
        return {n: t.grad[torch.from_numpy(trainable)] for n, t in p.items() if t.grad is not None}

    whole = grads(view)
    (crop,), (box,) = crop_views([view], [r], 12)
    assert crop.image.shape[0] * crop.image.shape[1] < 0.7 * cam.width * cam.height and 0 < crop.loss_scale < 1
    assert crop.camera.width == box[3] - box[2] and crop.camera.height == box[1] - box[0]
    part = grads(crop)
    scale = max(float(g.abs().max()) for g in whole.values())
    for n, g in whole.items():
        assert torch.allclose(part[n], g, rtol=1e-3, atol=1e-5 * scale), n
    (tight,), _ = crop_views([view], [r], 0)
    loose = grads(tight)
    assert any(not torch.allclose(loose[n], g, rtol=1e-3, atol=1e-5 * scale) for n, g in whole.items())
    (none,), (no_box,) = crop_views([view], [np.zeros_like(r)], 12)
    assert none is None and no_box is None


def test_the_finetune_on_crops_matches_the_whole_views(tmp_path):
    """``crop`` on (the default) trains on the crops and records them; its renders are those of the
    re-fit on the whole views up to float rounding."""
    inputs = plane_inputs(tmp_path / "in", side=40, w=128, h=96, hole_box=(0.42, 0.58), seed_extent=0.15)
    on, _, d_on = run_finetune(tmp_path / "on", inputs, device="cpu", crop_margin=12)
    off, _, d_off = run_finetune(tmp_path / "off", inputs, device="cpu", crop=False)
    assert "crop" not in off and on["crop"]["views"] == 4 and on["crop"]["views_left_out"] == 0
    assert 0 < on["crop"]["pixel_share"] < 0.8 and on["crop"]["reach_outside_at_end"] < 0.01
    for name in ("v0", "v1", "v2", "v3"):
        a = read_rgb8(d_on / "renders" / f"{name}.png").astype(np.float64) / 255
        b = read_rgb8(d_off / "renders" / f"{name}.png").astype(np.float64) / 255
        assert -10 * np.log10(((a - b) ** 2).mean() + 1e-12) > 45.0, name
    with pytest.raises(PipelineError, match="crop_margin"):
        run_finetune(tmp_path / "bad", inputs, device="cpu", crop_margin=-1)


def test_harmonize_moves_the_targets_mask_region_to_the_photos_colours(tmp_path):
    """finetune.harmonize: the target inside the object mask (the fill, the render after deletion) is
    corrected towards the photo around the mask (removal.harmonize); outside it the photo stays. Here the
    photos are brighter than the renders by 0.1 (another exposure): the hole's fill is lifted by about
    that much, and not without the option."""
    inputs = plane_inputs(tmp_path / "in")
    cams = load_cameras(inputs["remove"] / "cameras.json")
    (inputs["remove"] / "masks").mkdir()
    sfm = tmp_path / "in" / "sfm"
    (sfm / "images").mkdir(parents=True)
    for cam in cams:
        hole = read_mask(inputs["remove"] / "holes" / f"{cam.image}.png")
        write_mask01(inputs["remove"] / "masks" / f"{cam.image}.png", hole)  # (the mask is all hole here)
        fill = read_rgb8(inputs["refine"] / "images" / f"{cam.image}.png").astype(np.float32) / 255
        write_png(sfm / "images" / f"{cam.image}.png", np.clip(fill + 0.1, 0, 1))
    inputs = {**inputs, "sfm": sfm}
    cam = cams[0]
    hole = read_mask(inputs["remove"] / "holes" / f"{cam.image}.png")
    fill = read_rgb8(inputs["refine"] / "images" / f"{cam.image}.png").astype(np.float32) / 255
    views = {}
    for on in (False, True):
        ctx = StageContext.standalone(tmp_path / str(on), "finetune", FinetuneParams(max_size=0, harmonize=on), inputs)
        views[on] = FinetuneStage._view(ctx, cam, hole, ctx.params).image.numpy()
    inner = hole & ~np.pad(~hole, 4, constant_values=True)[4:-4, 4:-4]  # (inside, away from the band)
    np.testing.assert_allclose(views[False][inner], fill[inner], atol=1 / 255)
    lift = (views[True] - views[False])[inner]
    assert np.abs(lift - 0.1).mean() < 0.01
    ys, xs = hole.nonzero()
    far = np.ones_like(hole)
    far[ys.min() - 6:ys.max() + 7, xs.min() - 6:xs.max() + 7] = False  # (beyond the mask's band and ring)
    np.testing.assert_array_equal(views[True][far], views[False][far])  # the photo
    # a view larger than the training size: the correction is computed at that size and upsampled
    small = {}
    for on in (False, True):
        ctx = StageContext.standalone(tmp_path / f"s{on}", "finetune", FinetuneParams(max_size=32, harmonize=on),
                                      inputs)
        small[on] = FinetuneStage._view(ctx, cam, hole, ctx.params).image.numpy()
    assert small[True].shape == (24, 32, 3)
    inner_small = inner[::2, ::2] & inner[1::2, 1::2]
    assert np.abs((small[True] - small[False])[inner_small] - 0.1).mean() < 0.01
    with pytest.raises(PipelineError, match="harmonize_ring"):
        run_finetune(tmp_path / "bad", inputs, harmonize_ring=0)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA device"))])
def test_the_low_pass_term_leaves_the_detail_free(device):
    """``lowpass_l1`` (the finetune's ``hole_detail``): a render that differs from the target by a
    checkerboard (detail) costs almost nothing on the low-pass pixels, a colour offset costs its size;
    ``view_loss`` mixes it with the photometric loss as one mean over both sets of pixels, and passes a
    gradient only through what the blur keeps. On the CPU and, where there is one, on CUDA."""
    from sgpor_pipeline.gaussians.train import TrainView, lowpass_l1, photometric_loss, view_loss

    rng = np.random.default_rng(0)
    h, w = 40, 48
    target = torch.from_numpy(rng.random((h, w, 3)).astype(np.float32)).to(device)
    yy, xx = np.mgrid[0:h, 0:w]
    checker = torch.from_numpy(np.where((yy + xx) % 2 == 0, 0.2, -0.2).astype(np.float32)).to(device)
    checker = checker[..., None].expand(h, w, 3)
    low = torch.zeros(h, w, device=device)
    low[10:30, 12:36] = 1.0
    assert float((checker.abs() * low[..., None]).sum() / (low.sum() * 3)) == pytest.approx(0.2)
    assert float(lowpass_l1(target + checker, target, low, 2.0)) < 0.01
    assert float(lowpass_l1(target + 0.1, target, low, 2.0)) == pytest.approx(0.1, abs=1e-4)
    cam = Camera("v", w, h, np.array([[40.0, 0, w / 2], [0, 40.0, h / 2], [0, 0, 1]]), np.eye(4), image="v")
    plain = TrainView("v", target, cam)
    render = (target + 0.1).clone().requires_grad_(True)
    assert torch.equal(view_loss(render, plain, 0.2), photometric_loss(render, target, 0.2))
    weight = 1.0 - low
    mixed = TrainView("v", target, cam, weight=weight, lowpass=low, lowpass_sigma=2.0)
    n_full, n_low = float(weight.sum()), float(low.sum())
    expect = (photometric_loss(render, target, 0.0, weight) * n_full + 0.1 * n_low) / (n_full + n_low)
    assert float(view_loss(render, mixed, 0.0).detach()) == pytest.approx(float(expect.detach()), abs=1e-4)
    detail = (target + checker).clone().requires_grad_(True)
    lowpass_l1(detail, target, low, 2.0).backward()
    assert torch.isfinite(detail.grad).all() and float(detail.grad.abs().sum()) > 0
    assert float(detail.grad[:3].abs().max()) == 0.0  # (rows beyond the blur's reach of the low-pass pixels)


def _textured_fills(inputs: dict[str, Path], seed: int = 1) -> None:
    """Each view's fill of the hole made its own random texture (blobs of about 6 px) around one colour:
    fills that do not agree in their detail, as the views' own fills of a thick hole."""
    import cv2

    rng = np.random.default_rng(seed)
    for cam in load_cameras(inputs["remove"] / "cameras.json"):
        hole = read_mask(inputs["remove"] / "holes" / f"{cam.image}.png")
        img = read_rgb8(inputs["refine"] / "images" / f"{cam.image}.png").astype(np.float32) / 255
        noise = cv2.GaussianBlur(rng.standard_normal(hole.shape).astype(np.float32), (0, 0), 2.5)
        texture = np.clip(np.array([0.35, 0.55, 0.3], np.float32) + 1.2 * noise[..., None], 0, 1)
        write_png(inputs["refine"] / "images" / f"{cam.image}.png", np.where(hole[..., None], texture, img))


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA device"))])
def test_hole_detail_largest_keeps_the_largest_views_fill(tmp_path, device):
    """``hole_detail``: with "every" the re-fit averages the views' disagreeing textures; with
    "largest" the view with the most hole pixels keeps its own texture in the render (closer to its
    fill, with more of its detail) while every view's hole keeps the fills' colour. On the CPU and,
    where there is one, on CUDA (the low-pass term on the device, gsplat's renders where installed)."""
    import cv2

    inputs = plane_inputs(tmp_path / "in", side=60, w=96, h=72, hole_box=(0.3, 0.7), seed_extent=0.45)
    _textured_fills(inputs)
    cams = load_cameras(inputs["remove"] / "cameras.json")
    hole = read_mask(inputs["remove"] / "holes" / "v0.png")
    inner = cv2.erode(hole.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0

    def score(out: Path, name: str) -> tuple[float, float, float]:
        """PSNR of the render against the view's fill, the render's texture contrast (std) over the
        fill's, and the largest channel's difference of their means, in the hole."""
        render = read_rgb8(out / "renders" / f"{name}.png").astype(np.float64)[inner] / 255
        fill = read_rgb8(inputs["refine"] / "images" / f"{name}.png").astype(np.float64)[inner] / 255
        return (-10 * np.log10(((render - fill) ** 2).mean()), float(render.std(0).mean() / fill.std(0).mean()),
                float(np.abs(render.mean(0) - fill.mean(0)).max()))

    runs = {mode: run_finetune(tmp_path / mode, inputs, device=device, iterations=300, hole_detail=mode)
            for mode in ("every", "largest")}
    every, largest = (score(runs[m][2], "v0") for m in ("every", "largest"))  # (v0: the first of equal holes)
    assert largest[0] > every[0] + 2.0, (every, largest)
    for cam in cams[1:]:  # the other views' holes: the colour as with "every"
        assert score(runs["largest"][2], cam.image)[2] < score(runs["every"][2], cam.image)[2] + 0.02, cam.image
    assert runs["largest"][0]["hole_detail"]["view"] == "v0" and "hole_detail" not in runs["every"][0]
    # with the inpaint stage's record only the pixels a view filled on its own count: v2 filled all of
    # its hole on its own, the others took the left half of theirs from elsewhere (consistent)
    assert FinetuneStage.upstream(FinetuneParams()) == ("sfm", "remove", "refine")
    assert "inpaint" in FinetuneStage.upstream(FinetuneParams(hole_detail="largest"))
    filled = tmp_path / "in" / "inpaint" / "filled_from"
    filled.mkdir(parents=True)
    half = hole & (np.arange(hole.shape[1]) >= hole.shape[1] // 2)[None]
    for cam in cams:
        own = hole if cam.image == "v2" else half
        write_labels(filled / f"{cam.image}.png", np.where(own, 2, hole).astype(np.uint8))
    info = run_finetune(tmp_path / "record", {**inputs, "inpaint": filled.parent}, device=device, iterations=2,
                        hole_detail="largest")[0]["hole_detail"]
    assert info == {"view": "v2", "own_pixels": int(hole.sum()), "lowpass_pixels": 3 * int(half.sum()),
                    "views_following": 3}
    with pytest.raises(PipelineError, match="hole_detail"):
        run_finetune(tmp_path / "bad", inputs, hole_detail="median")


def test_only_the_views_that_see_the_holes_like_the_reference_follow_it():
    """``like_the_reference`` (hole_detail): a view follows the largest view only when it sees the holes
    from about its distance and direction: along a street (a forward capture whose nearest view has
    the largest hole) none of the far views does; around an object the near-by views of an arc do,
    the far side of the ring does not."""
    from sgpor_pipeline.stages.finetune import like_the_reference

    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])

    def looking_at(centre: np.ndarray, target: np.ndarray, name: str) -> Camera:
        z = (target - centre) / np.linalg.norm(target - centre)
        x = np.cross([0.0, -1.0, 0.0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, -R @ centre
        return Camera(name, 64, 48, K, T, image=name)

    hole = np.array([[0.0, 0.0, 10.0], [0.2, 0.1, 10.2]])
    street = [looking_at(np.array([0.0, 0.0, z]), hole.mean(0), f"s{i}") for i, z in enumerate((-30, -20, -10, 7))]
    assert like_the_reference(street, 3, hole, 1.5).tolist() == [False, False, False, True]
    # (distances 40, 30, 20 and 3: from the second, 1.33x and 0.67x)
    assert like_the_reference(street, 1, hole, 1.5).tolist() == [True, True, True, False]
    assert like_the_reference(street, 1, hole, 1.2).tolist() == [False, True, False, False]
    angles = np.radians([0, 10, 20, 180])
    ring = [looking_at(np.array([5 * np.sin(a), 0.0, 10 - 5 * np.cos(a)]), hole.mean(0), f"r{i}")
            for i, a in enumerate(angles)]
    assert like_the_reference(ring, 0, hole, 1.5).tolist() == [True, True, True, False]
    assert like_the_reference(ring, 0, np.zeros((0, 3)), 1.5).all()
