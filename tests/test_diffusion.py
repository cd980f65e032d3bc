"""The optional diffusion backend (inpaint) and the SDS term (finetune).

These tests use a TINY randomly initialised Stable-Diffusion-inpainting-shaped model built from
configs and saved into tmp_path (no download, no real weights): they check shapes, dtypes, finite
values, gradients, cache keys, errors and the stage plumbing only, NOT inpainting quality (a random
model paints noise). The tests that need diffusers/transformers are skipped when they are not
installed (``pip install 'sgpor-pipeline[diffusion]'``); the error tests run either way.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from sgpor_pipeline.dag import StageContext
from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.hashing import hash_obj
from sgpor_pipeline.imageio import read_image, write_mask01, write_png
from sgpor_pipeline.removal import diffusion as sd
from sgpor_pipeline.scene import Camera, save_cameras

# --------------------------------------------------------------------------------------------------
# helpers


def make_tiny_model(folder: Path, seed: int = 0) -> Path:
    """A tiny inpainting model in the diffusers layout (UNet in_channels 9, VAE, CLIP text encoder,
    a tokenizer from a 54-token vocabulary written here, DDIM scheduler): random weights, ~0.5 MB."""
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

    torch.manual_seed(seed)
    unet = UNet2DConditionModel(sample_size=8, in_channels=9, out_channels=4, block_out_channels=(8, 16),
                                layers_per_block=1, down_block_types=("DownBlock2D", "CrossAttnDownBlock2D"),
                                up_block_types=("CrossAttnUpBlock2D", "UpBlock2D"), cross_attention_dim=16,
                                attention_head_dim=4, norm_num_groups=4)
    vae = AutoencoderKL(in_channels=3, out_channels=3, block_out_channels=(8, 16), layers_per_block=1,
                        latent_channels=4, down_block_types=("DownEncoderBlock2D",) * 2,
                        up_block_types=("UpDecoderBlock2D",) * 2, norm_num_groups=4, sample_size=16)
    text = CLIPTextModel(CLIPTextConfig(vocab_size=64, hidden_size=16, intermediate_size=32, num_hidden_layers=1,
                                        num_attention_heads=2, max_position_embeddings=16, bos_token_id=0,
                                        eos_token_id=1, pad_token_id=1))
    sched = DDIMScheduler(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", clip_sample=False,
                          set_alpha_to_one=False)
    for name, module in (("unet", unet), ("vae", vae), ("text_encoder", text), ("scheduler", sched)):
        module.save_pretrained(folder / name)
    tok_dir = folder / "tokenizer"
    tok_dir.mkdir(parents=True, exist_ok=True)
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for c in "abcdefghijklmnopqrstuvwxyz":
        vocab[c] = len(vocab)
        vocab[c + "</w>"] = len(vocab)
    (tok_dir / "vocab.json").write_text(json.dumps(vocab))
    (tok_dir / "merges.txt").write_text("#version: 0.2\n")
    tokenizer = CLIPTokenizer(str(tok_dir / "vocab.json"), str(tok_dir / "merges.txt"), model_max_length=16)
    tokenizer.save_pretrained(tok_dir)
    (folder / "model_index.json").write_text(json.dumps({"_class_name": "StableDiffusionInpaintPipeline"}))
    return folder


@pytest.fixture(scope="module")
def weights(tmp_path_factory) -> tuple[Path, Path]:
    """Two tiny weights folders that differ only in their random weights."""
    pytest.importorskip("diffusers")
    pytest.importorskip("transformers")
    root = tmp_path_factory.mktemp("weights")
    return make_tiny_model(root / "a", seed=0), make_tiny_model(root / "b", seed=1)


@pytest.fixture(scope="module")
def tiny(weights) -> sd.DiffusionModel:
    return sd.load_model(sd.resolve_model_dir(str(weights[0])))




def textured(h: int, w: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:h, 0:w]
    img = np.stack([0.5 + 0.3 * np.sin(xs / 3.0), 0.5 + 0.3 * np.cos(ys / 4.0), 0.5 + 0.2 * np.sin((xs + ys) / 5.0)],
                   axis=2)
    return np.clip(img + 0.05 * rng.standard_normal((h, w, 3)), 0, 1).astype(np.float32)


def plane_scene(n: int = 400, w: int = 40, h: int = 30, seed: int = 0):
    """Gaussians on a textured plane at z = 2 in front of two cameras, and a hole in the middle."""
    from sgpor_pipeline.gaussians.model import GaussianModel, rgb_to_sh

    rng = np.random.default_rng(seed)
    side = int(np.sqrt(n))
    g = np.linspace(-1.2, 1.2, side)
    X, Y = np.meshgrid(g, g)
    xyz = np.stack([X.ravel(), Y.ravel(), np.full(X.size, 2.0)], axis=1)
    model = GaussianModel.empty(len(xyz), 0)
    with torch.no_grad():
        model.params["means"].copy_(torch.from_numpy(xyz).float())
        model.params["scales"].fill_(float(np.log(2.4 / side)))
        model.params["opacities"].fill_(2.0)
        model.params["sh0"].copy_(rgb_to_sh(torch.from_numpy(rng.random((len(xyz), 3))).float())[:, None, :])
    K = np.array([[w * 0.8, 0, w / 2], [0, w * 0.8, h / 2], [0, 0, 1.0]])
    cams = []
    for i, dx in enumerate((0.0, 0.15)):
        T = np.eye(4)
        T[0, 3] = -dx
        cams.append(Camera(f"v{i}", w, h, K, T, image=f"v{i}"))
    hole = np.zeros((h, w), bool)
    hole[h // 3: 2 * h // 3, w // 3: 2 * w // 3] = True
    return model, cams, [hole.copy() for _ in cams]


# --------------------------------------------------------------------------------------------------
# errors (run with or without diffusers)


def test_missing_weights_is_a_clear_error(tmp_path, monkeypatch):
    """Plumbing only: the error names the config key, the env var, the folder layout and the extra."""
    monkeypatch.delenv(sd.ENV_VAR, raising=False)
    with pytest.raises(PipelineError) as e:
        sd.resolve_model_dir("", "inpaint.diffusion_model")
    msg = str(e.value)
    for needed in ("inpaint.diffusion_model", sd.ENV_VAR, "unet/", "in_channels = 9", "tokenizer/",
                   "pip install 'sgpor-pipeline[diffusion]'"):
        assert needed in msg, (needed, msg)
    # a folder that lacks components: say which
    (tmp_path / "w" / "unet").mkdir(parents=True)
    monkeypatch.setenv(sd.ENV_VAR, str(tmp_path / "w"))
    with pytest.raises(PipelineError, match=r"lacks vae/, text_encoder/, tokenizer/, scheduler/") as e:
        sd.resolve_model_dir("")
    assert sd.ENV_VAR in str(e.value)
    with pytest.raises(PipelineError, match="does not exist"):
        sd.resolve_model_dir(str(tmp_path / "nowhere"))
    # a text-to-image (4-channel) UNet is not an inpainting model
    for comp in sd.COMPONENTS:
        (tmp_path / "w" / comp).mkdir(exist_ok=True)
    for comp in ("unet", "vae", "text_encoder"):
        (tmp_path / "w" / comp / "config.json").write_text(json.dumps({"in_channels": 4}))
        (tmp_path / "w" / comp / "model.safetensors").write_bytes(b"x")
    with pytest.raises(PipelineError, match="not an inpainting model"):
        sd.resolve_model_dir(str(tmp_path / "w"))


def test_missing_diffusers_is_a_clear_error(tmp_path, monkeypatch):
    """Plumbing only: with diffusers hidden, naming the backend (or lambda_sds > 0) fails before any
    work with the extra to install; ``auto`` falls back to SBM and says why."""
    from sgpor_pipeline.stages.finetune import FinetuneParams, FinetuneStage
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage, resolve_backend

    monkeypatch.setitem(sys.modules, "diffusers", None)  # import diffusers -> ImportError
    monkeypatch.setenv(sd.ENV_VAR, str(tmp_path / "weights"))
    assert not sd.diffusers_available()
    with pytest.raises(PipelineError, match=r"pip install 'sgpor-pipeline\[diffusion\]'"):
        sd.require_diffusers()
    backend, why = resolve_backend(InpaintParams(backend="auto"))
    assert backend == "sbm" and "not installed" in why and "sgpor-pipeline[diffusion]" in why
    assert InpaintStage.key_extra(InpaintParams(backend="auto")) == {}
    # the remove folder does not exist: the error must come first, before reading anything
    ctx = StageContext.standalone(tmp_path, "inpaint", InpaintParams(backend="diffusion"),
                                  {"remove": tmp_path / "none"})
    with pytest.raises(PipelineError, match="diffusers"):
        InpaintStage().run(ctx)
    ctx = StageContext.standalone(tmp_path, "finetune", FinetuneParams(lambda_sds=0.1),
                    {"remove": tmp_path / "none", "refine": tmp_path / "none"})
    with pytest.raises(PipelineError, match=r"sgpor-pipeline\[diffusion\]"):
        FinetuneStage().run(ctx)


# --------------------------------------------------------------------------------------------------
# with the tiny model


def test_refine_fill_shapes_and_untouched_outside(tiny):
    """Shapes, dtype, finite values; pixels outside the region bit-identical (not quality)."""
    img = textured(48, 64)
    region = np.zeros((48, 64), bool)
    region[15:30, 20:41] = True
    for blend in ("poisson", "paste"):
        out = sd.refine_fill(tiny, img, region, sd.DiffusionParams(resolution=32, steps=4, blend=blend), seed=3)
        assert out.shape == img.shape and out.dtype == np.float32
        assert np.isfinite(out).all() and out.min() >= 0 and out.max() <= 1
        assert np.array_equal(out[~region], img[~region])
        assert np.abs(out[region] - img[region]).mean() > 1e-3  # the model did change the hole
    again = sd.refine_fill(tiny, img, region, sd.DiffusionParams(resolution=32, steps=4, blend="paste"), seed=3)
    assert np.array_equal(again, out)  # seeded
    assert np.array_equal(sd.refine_fill(tiny, img, np.zeros_like(region), sd.DiffusionParams()), img)
    with pytest.raises(PipelineError, match="strength"):
        sd.refine_fill(tiny, img, region, sd.DiffusionParams(strength=0.0))


def test_inpaint_stage_diffusion_backend_multiview_and_cache(weights, tiny, tmp_path, monkeypatch):
    """The stage runs SBM, then the tiny model on what SBM inpainted, keeping the multi-view scheme;
    the report says which backend ran and why; new weights rebuild the items. Plumbing, not quality."""
    from sgpor_pipeline.removal.multiview import write_remove_fixture
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage
    from sgpor_pipeline.synthetic import SceneParams, generate_scene

    scene = generate_scene(SceneParams(seed=0, rig="forward", n_views=3, width=64, height=48))
    remove = write_remove_fixture(scene, tmp_path / "remove", holes="mask")
    monkeypatch.delenv(sd.ENV_VAR, raising=False)
    # carry_max_rim 0: the fixture's depth is exact, every part of a hole is carried (multi-view plumbing)
    small = {"diffusion_resolution": 32, "diffusion_steps": 4, "block_size": 9, "carry_max_rim": 0,
             "reference": "largest"}  # (one reference: only what a view inpainted itself is refined)
    builds: list = []
    params = InpaintParams(backend="diffusion", diffusion_model=str(weights[0]), **small)
    ctx = StageContext.standalone(tmp_path, "inpaint", params, {"remove": remove}, builds)
    InpaintStage().run(ctx)
    report = json.loads((ctx.out_dir / "inpaint.json").read_text())
    assert report["backend"] == "diffusion" and report["backend_requested"] == "diffusion"
    assert report["backend_reason"] == "named in the config"
    assert report["multiview"] and report["projected"] > 0
    assert report["diffusion"]["folder"] == str(weights[0]) and report["diffusion"]["pixels"] > 0
    ref = report["reference"]
    assert report["views"][ref]["diffusion_pixels"] == report["views"][ref]["hole_pixels"]
    sbm_ctx = StageContext.standalone(tmp_path / "sbm", "inpaint", InpaintParams(backend="sbm", **small),
                                      {"remove": remove})
    InpaintStage().run(sbm_ctx)
    for i, cam in enumerate(scene.cameras):
        img = read_image(ctx.out_dir / "images" / f"{cam.name}.png")
        render = read_image(remove / "renders" / f"{cam.name}.png")
        hole = scene.masks[i]
        assert img.shape == (48, 64, 3) and np.isfinite(img).all()
        assert np.array_equal(img[~hole], render[~hole])
        ff = np.asarray(__import__("cv2").imread(str(ctx.out_dir / "filled_from" / f"{cam.name}.png"), -1))
        assert np.array_equal(ff > 0, hole)
        if cam.name == ref:
            sbm_img = read_image(sbm_ctx.out_dir / "images" / f"{cam.name}.png")
            assert np.abs(img[hole] - sbm_img[hole]).mean() > 1e-3  # the diffusion step ran on top of SBM
    n = len(builds)
    assert n == 3
    InpaintStage().run(StageContext.standalone(tmp_path, "inpaint", params, {"remove": remove}, builds))
    assert len(builds) == n  # cached items
    # the same configuration with the weights named by the environment variable instead: another
    # folder means other items (item keys do not contain key_extra, the stage adds the weights itself)
    monkeypatch.setenv(sd.ENV_VAR, str(weights[1]))
    p_env = InpaintParams(backend="auto", **small)
    ctx_b = StageContext.standalone(tmp_path, "inpaint", p_env, {"remove": remove}, builds)
    InpaintStage().run(ctx_b)
    report_b = json.loads((ctx_b.out_dir / "inpaint.json").read_text())
    assert report_b["backend"] == "diffusion" and report_b["backend_requested"] == "auto"
    assert report_b["backend_reason"].startswith("auto: ") and str(weights[1]) in report_b["backend_reason"]
    assert len(builds) == n + 3


def test_cache_key_follows_the_weights_folder(weights, tmp_path, monkeypatch):
    """key_extra (which enters the stage key) changes with the resolved weights; sbm keys ignore them.
    Plumbing only, not quality."""
    from sgpor_pipeline.stages.finetune import FinetuneParams, FinetuneStage
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage, resolve_backend

    a, b = weights
    monkeypatch.delenv(sd.ENV_VAR, raising=False)
    assert resolve_backend(InpaintParams(backend="auto"))[0] == "sbm"
    assert InpaintStage.key_extra(InpaintParams(backend="auto")) == {}
    keys = {}
    for name, folder in (("a", a), ("b", b), ("a2", a)):
        monkeypatch.setenv(sd.ENV_VAR, str(folder))
        keys[name] = (InpaintStage.key_extra(InpaintParams(backend="diffusion")),
                      InpaintStage.key_extra(InpaintParams(backend="auto")),
                      InpaintStage.key_extra(InpaintParams(backend="sbm")),
                      FinetuneStage.key_extra(FinetuneParams(lambda_sds=0.1)),
                      FinetuneStage.key_extra(FinetuneParams()))
    assert keys["a"] == keys["a2"]
    assert keys["a"][0] == keys["a"][1] and keys["a"][0]["diffusion"]["folder"] == str(a)
    assert hash_obj(keys["a"][0]) != hash_obj(keys["b"][0])
    assert hash_obj(keys["a"][3]) != hash_obj(keys["b"][3])
    assert keys["a"][2] == keys["b"][2] == {} and keys["a"][4] == keys["b"][4] == {}
    # the same files in another folder: the folder is part of the key (as asked), so is the content
    copy = tmp_path / "copy"
    shutil.copytree(a, copy)
    monkeypatch.setenv(sd.ENV_VAR, str(copy))
    k_copy = InpaintStage.key_extra(InpaintParams(backend="diffusion"))["diffusion"]
    assert k_copy["content"] == keys["a"][0]["diffusion"]["content"] and k_copy["folder"] != str(a)
    # the config setting wins over the environment variable
    assert InpaintStage.key_extra(InpaintParams(backend="diffusion", diffusion_model=str(b)))["diffusion"][
        "folder"] == str(b)


def test_sds_loss_gives_gradients_to_render_and_gaussians(weights, tiny):
    """SDS: finite, non-zero gradients on the rendered image and the Gaussians (not quality)."""
    from sgpor_pipeline.stages.finetune import FinetuneParams, SDSFocusStrategy, SDSTerm

    model, cams, holes = plane_scene()
    p = FinetuneParams(lambda_sds=1.0, sds_resolution=32, iterations=8, sds_steps=4, diffusion_model=str(weights[0]),
                       backend="cpu")
    term = SDSTerm(tiny, cams, holes, p)
    assert term.every == 2 and len(term.views) == 2
    cam, hole = term.views[0]
    assert (cam.height % tiny.multiple, cam.width % tiny.multiple) == (0, 0) and hole.shape == (cam.height, cam.width)
    render = term.render(model, cam)
    render.retain_grad()
    loss = sd.sds_loss(tiny, render, hole, p.sds(), torch.Generator().manual_seed(0), term.embeddings)
    assert loss.dim() == 0 and torch.isfinite(loss)
    loss.backward()
    g = render.grad
    assert g.shape == render.shape and torch.isfinite(g).all() and g.abs().sum() > 0
    assert g[hole].abs().mean() > g[~hole].abs().mean()  # the hole is what is distilled
    for name in ("means", "sh0", "opacities", "scales"):
        grad = model.params[name].grad
        assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0, name
    # through the strategy hook the trainer calls: only on the scheduled iterations
    for q in model.params.values():
        q.grad = None
    strat = SDSFocusStrategy(torch.ones(len(model), dtype=torch.bool), term)
    assert strat.extra_loss(model, 1) is None
    extra = strat.extra_loss(model, 2)
    assert extra is not None and torch.isfinite(extra)
    extra.backward()
    assert model.params["sh0"].grad.abs().sum() > 0 and term.calls == 1


def test_finetune_stage_with_sds_runs(weights, tmp_path, monkeypatch):
    """The finetune stage with lambda_sds > 0 trains with the SDS term. Plumbing only (it ran, the
    values are finite), NOT quality."""
    from sgpor_pipeline.gaussians.ply import read_ply, write_ply
    from sgpor_pipeline.stages.finetune import FinetuneParams, FinetuneStage

    model, cams, holes = plane_scene()
    remove, refine = tmp_path / "remove", tmp_path / "refine"
    for sub in (remove / "holes", refine / "images"):
        sub.mkdir(parents=True)
    write_ply(remove / "gaussians.ply", model)
    hole_ids = np.flatnonzero(np.abs(model.params["means"][:, :2].detach().numpy()).max(axis=1) < 0.3)
    np.save(remove / "seed_ids.npy", hole_ids)
    save_cameras(remove / "cameras.json", cams)
    for cam, hole in zip(cams, holes):
        write_mask01(remove / "holes" / f"{cam.image}.png", hole)
        write_png(refine / "images" / f"{cam.image}.png", textured(cam.height, cam.width))
    monkeypatch.setenv(sd.ENV_VAR, str(weights[0]))
    p = FinetuneParams(iterations=6, lambda_sds=0.5, sds_steps=3, sds_resolution=32, max_size=0, backend="cpu")
    ctx = StageContext.standalone(tmp_path, "finetune", p, {"remove": remove, "refine": refine})
    FinetuneStage().run(ctx)
    info = json.loads((ctx.out_dir / "finetune.json").read_text())
    assert info["trainable"] > 0 and info["iterations"] == 6
    assert info["sds"]["steps"] == 3 and info["sds"]["model"] == str(weights[0])
    assert np.isfinite(info["sds"]["mean_loss"])
    out = read_ply(ctx.out_dir / "gaussians.ply")
    assert all(torch.isfinite(v).all() for v in out.params.values())
    # without weights, lambda_sds > 0 is a clear error
    monkeypatch.delenv(sd.ENV_VAR)
    with pytest.raises(PipelineError, match="finetune.diffusion_model"):
        FinetuneStage().run(StageContext.standalone(tmp_path / "x", "finetune", p,
                                                    {"remove": remove, "refine": refine}))
