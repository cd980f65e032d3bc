"""Optional diffusion backend: Stable Diffusion inpainting (diffusers) from LOCAL weights, and an SDS loss.

The paper (DESIGN.md section 7) uses Stable Diffusion inpainting for the initial fill and an SDS term
in the final re-fit. Here both are optional (extra ``pip install 'sgpor-pipeline[diffusion]'``) and
never download anything: the weights are a local folder named in the config (``diffusion_model`` of
the inpaint / finetune stage) or by the environment variable ``SGPOR_DIFFUSION_MODEL``, in the
diffusers layout (:data:`LAYOUT`), e.g. a local copy of ``stable-diffusion-v1-5/stable-diffusion-inpainting``.

* :func:`refine_fill` is conditioned on the SBM match: the SBM fill of the hole is the init image
  (img2img: noised to ``strength`` < 1 of the schedule, then denoised by the inpainting UNet that
  also sees the masked image), so diffusion refines the semantic-guided match instead of
  hallucinating from scratch. Only the given region changes; pixels outside it are bit-identical.
  The inpaint stage keeps its multi-view scheme (reference view first, lifted to 3D and projected,
  only what is still missing inpainted): this function runs on the pixels SBM filled in each view.
* :func:`sds_loss` is Score Distillation Sampling on a render of the hole region: the render's VAE
  latent is noised at a random timestep, the UNet (conditioned on the masked render) predicts the
  noise, and ``w(t) (eps_pred - eps)`` is the gradient pushed into the latent, hence through the VAE
  encoder into the rendered image and the Gaussians.

The tests (tests/test_diffusion.py) use a tiny randomly initialised model: they check shapes,
gradients and plumbing only, NOT inpainting quality.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from sgpor_pipeline.errors import PipelineError

ENV_VAR = "SGPOR_DIFFUSION_MODEL"
INSTALL = "pip install 'sgpor-pipeline[diffusion]'"
COMPONENTS = ("unet", "vae", "text_encoder", "tokenizer", "scheduler")
LAYOUT = ("a diffusers Stable Diffusion INPAINTING folder: [model_index.json,] unet/ (config.json with "
          "in_channels = 9, diffusion_pytorch_model[.fp16].safetensors), vae/ (config.json + weights), "
          "text_encoder/ (config.json + model[.fp16].safetensors), tokenizer/ (vocab.json, merges.txt), "
          "scheduler/ (scheduler_config.json); e.g. a local copy of stable-diffusion-v1-5/"
          "stable-diffusion-inpainting")
_WEIGHT_SUFFIXES = (".safetensors", ".bin")
_SMALL_FILE = 16 << 20  # files up to this size are hashed whole; larger ones by size, head and tail
_SAMPLE = 4 << 20


# --------------------------------------------------------------------------------------------------
# availability, configuration, clear errors


def diffusers_available() -> bool:
    """Whether diffusers and transformers can be imported (checked without importing them: slow)."""
    try:
        return all(importlib.util.find_spec(m) is not None for m in ("diffusers", "transformers"))
    except (ImportError, ValueError):
        return False


def require_diffusers() -> None:
    """Import diffusers and transformers, or raise a PipelineError naming the extra to install."""
    try:
        import diffusers  # noqa: F401
        import transformers  # noqa: F401
    except ImportError as e:
        missing = getattr(e, "name", None) or "diffusers"
        raise PipelineError(f"the diffusion backend needs diffusers and transformers, and {missing} is not installed",
                            fix=f"{INSTALL} (about 35 MB of wheels; the installed torch is kept)"
                            ) from None


def configured_model(setting: str, env: Mapping[str, str] | None = None) -> str:
    """The weights folder as configured: ``setting`` (the stage's ``diffusion_model``) or else the
    environment variable :data:`ENV_VAR`; "" when neither is set."""
    env = os.environ if env is None else env
    return setting.strip() or env.get(ENV_VAR, "").strip()


def _missing_weights_error(config_key: str) -> PipelineError:
    return PipelineError(
        "the diffusion backend needs local Stable Diffusion inpainting weights, and none are configured "
        "(nothing is ever downloaded)",
        fix=f"set {config_key} = \"/path/to/weights\" in the config (or --set {config_key}=...) or the "
            f"environment variable {ENV_VAR}; the folder must be {LAYOUT}; and {INSTALL}")


def resolve_model_dir(setting: str, config_key: str = "inpaint.diffusion_model",
                      env: Mapping[str, str] | None = None) -> Path:
    """The configured weights folder, resolved and checked (layout, an inpainting UNet, weight files).

    Raises a PipelineError that says what to provide when nothing is configured or the folder is wrong.
    """
    raw = configured_model(setting, env)
    if not raw:
        raise _missing_weights_error(config_key)
    folder = Path(raw).expanduser().resolve()
    source = f"{config_key}" if setting.strip() else f"${ENV_VAR}"
    if not folder.is_dir():
        raise PipelineError(f"the diffusion weights folder (from {source}) does not exist", path=folder,
                            fix=f"point {config_key} or {ENV_VAR} at {LAYOUT}")
    missing = [c for c in COMPONENTS if not (folder / c).is_dir()]
    if missing:
        raise PipelineError(f"the diffusion weights folder (from {source}) lacks {', '.join(m + '/' for m in missing)}",
                            path=folder, fix=f"the folder must be {LAYOUT}")
    for comp in ("unet", "vae", "text_encoder"):
        if not (folder / comp / "config.json").is_file() or not _weight_files(folder / comp):
            raise PipelineError(f"{comp}/ has no config.json or no weights (*.safetensors / *.bin)", path=folder / comp,
                                fix=f"copy the complete folder: {LAYOUT}")
    try:
        in_ch = json.loads((folder / "unet" / "config.json").read_text()).get("in_channels")
    except ValueError as e:
        raise PipelineError(f"unet/config.json is not valid JSON ({e})", path=folder / "unet" / "config.json",
                            fix="copy the complete weights folder again") from None
    if in_ch != 9:
        raise PipelineError(f"the UNet has in_channels = {in_ch}: not an inpainting model (needs 9: latent, mask, "
                            "masked-image latent)", path=folder / "unet",
                            fix="use Stable Diffusion INPAINTING weights, e.g. stable-diffusion-inpainting")
    return folder


def auto_choice(setting: str, env: Mapping[str, str] | None = None) -> tuple[bool, str]:
    """For ``backend = "auto"``: (use diffusion?, why). Diffusion when weights are configured AND
    diffusers is importable; a configured but broken folder is still an error (at load time)."""
    raw = configured_model(setting, env)
    if not raw:
        return False, f"no diffusion weights configured (diffusion_model / ${ENV_VAR})"
    if not diffusers_available():
        return False, (f"diffusion weights are configured ({raw}) but diffusers/transformers are not "
                       f"installed ({INSTALL})")
    return True, f"diffusion weights configured ({raw}) and diffusers installed"


def _weight_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.name.endswith(_WEIGHT_SUFFIXES))


def _file_fingerprint(path: Path) -> str:
    """Content digest; for big files (the weights) size + first and last 4 MB: two different
    trainings differ there, and hashing gigabytes at every key computation would cost seconds."""
    size = path.stat().st_size
    h = hashlib.blake2b(digest_size=20)
    h.update(str(size).encode())
    with open(path, "rb") as f:
        if size <= _SMALL_FILE:
            h.update(f.read())
        else:
            h.update(f.read(_SAMPLE))
            f.seek(size - _SAMPLE)
            h.update(f.read(_SAMPLE))
    return h.hexdigest()


def weights_fingerprint(folder: Path) -> dict[str, Any]:
    """What the diffusion output depends on, for cache keys: the resolved folder, a content
    fingerprint of the files the backend loads, and the versions of diffusers and transformers."""
    from importlib.metadata import PackageNotFoundError, version

    folder = Path(folder)
    listing = []
    for comp in ("model_index.json",) + COMPONENTS:
        p = folder / comp
        files = [p] if p.is_file() else sorted(q for q in p.rglob("*") if q.is_file()) if p.is_dir() else []
        for q in files:
            if not any(part.startswith(".") for part in q.relative_to(folder).parts):
                listing.append((q.relative_to(folder).as_posix(), _file_fingerprint(q)))
    versions = {}
    for lib in ("diffusers", "transformers"):
        try:
            versions[lib] = version(lib)
        except PackageNotFoundError:
            versions[lib] = None
    content = hashlib.blake2b(json.dumps(listing).encode(), digest_size=20).hexdigest()
    return {"folder": str(folder), "content": content, "versions": versions}


# --------------------------------------------------------------------------------------------------
# the model


@dataclass
class DiffusionModel:
    """The loaded components (float32, eval mode, frozen) and helpers shared by inpainting and SDS."""

    folder: Path
    unet: Any
    vae: Any
    text_encoder: Any
    tokenizer: Any
    scheduler: Any  # DDIM, built from the folder's scheduler config

    @property
    def latent_factor(self) -> int:
        return 2 ** (len(self.vae.config.block_out_channels) - 1)

    @property
    def multiple(self) -> int:
        """Image sides must be multiples of this (VAE and UNet downsampling)."""
        return self.latent_factor * 2 ** (len(self.unet.config.block_out_channels) - 1)

    def text_embeddings(self, prompt: str) -> torch.Tensor:
        tok = self.tokenizer(prompt, padding="max_length", max_length=self.tokenizer.model_max_length,
                             truncation=True, return_tensors="pt")
        with torch.no_grad():
            return self.text_encoder(tok.input_ids)[0]

    def encode(self, image01: torch.Tensor) -> torch.Tensor:
        """Scaled VAE latent (the posterior mean: deterministic) of [B,3,H,W] images in [0,1];
        differentiable with respect to the images."""
        cfg = self.vae.config
        lat = self.vae.encode(image01 * 2.0 - 1.0).latent_dist.mean
        shift = getattr(cfg, "shift_factor", None) or 0.0
        return (lat - shift) * cfg.scaling_factor

    def decode(self, latents: torch.Tensor) -> torch.Tensor:
        cfg = self.vae.config
        shift = getattr(cfg, "shift_factor", None) or 0.0
        img = self.vae.decode(latents / cfg.scaling_factor + shift).sample
        return ((img + 1.0) / 2.0).clamp(0.0, 1.0)

    def condition(self, image01: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The inpainting UNet's extra inputs: the mask at latent size and the masked image's latent
        (hole pixels set to 0 in [-1, 1], i.e. grey, as diffusers' inpainting pipeline does)."""
        with torch.no_grad():
            masked = image01 * (mask < 0.5) + 0.5 * (mask >= 0.5)
            masked_lat = self.encode(masked)
            mask_lat = F.interpolate(mask, size=masked_lat.shape[-2:])
        return mask_lat, masked_lat

    def predict_noise(self, noisy: torch.Tensor, t: torch.Tensor, mask_lat: torch.Tensor, masked_lat: torch.Tensor,
                      cond: torch.Tensor, uncond: torch.Tensor | None, guidance: float) -> torch.Tensor:
        """UNet noise prediction, with classifier-free guidance when ``guidance`` != 1 (two passes)."""
        with torch.no_grad():
            x = torch.cat([noisy, mask_lat, masked_lat], dim=1)
            if uncond is None or guidance == 1.0:
                return self.unet(x, t, encoder_hidden_states=cond).sample
            eps = self.unet(torch.cat([x, x]), t, encoder_hidden_states=torch.cat([uncond, cond])).sample
            e_u, e_c = eps.chunk(2)
            return e_u + guidance * (e_c - e_u)


def _variant(comp_dir: Path) -> str | None:
    """The diffusers ``variant`` to load: None when plain weights exist (``model.safetensors``), else
    the tag of e.g. ``diffusion_pytorch_model.fp16.safetensors`` (or its shards ``.fp16-00001-of-00002``)."""
    names = [p.name for p in _weight_files(comp_dir)]
    if any(n.count(".") == 1 for n in names):
        return None
    for n in names:
        parts = n.split(".")
        if len(parts) == 3:
            return parts[1].split("-")[0]
    return None


def load_model(folder: Path) -> DiffusionModel:
    """Load a checked weights folder (:func:`resolve_model_dir`) on the CPU in float32, offline."""
    require_diffusers()
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPTextModel, CLIPTokenizer

    folder = Path(folder)

    def load(cls: Any, comp: str) -> Any:
        kw: dict[str, Any] = {"subfolder": comp, "local_files_only": True}
        v = _variant(folder / comp)
        if v is not None:
            kw["variant"] = v
        try:
            m = cls.from_pretrained(str(folder), **kw)
        except Exception as e:  # a damaged/incomplete folder: say which component
            raise PipelineError(f"cannot load the diffusion model's {comp}/ ({type(e).__name__}: {e})",
                                path=folder / comp, fix=f"copy the complete folder: {LAYOUT}") from e
        return m.float().eval().requires_grad_(False)

    unet = load(UNet2DConditionModel, "unet")
    vae = load(AutoencoderKL, "vae")
    text_encoder = load(CLIPTextModel, "text_encoder")
    try:
        tokenizer = CLIPTokenizer.from_pretrained(str(folder), subfolder="tokenizer", local_files_only=True)
        # img2img needs DDIM-style deterministic stepping whatever scheduler the folder names
        scheduler = DDIMScheduler.from_config(DDIMScheduler.load_config(str(folder), subfolder="scheduler",
                                                                       local_files_only=True))
    except Exception as e:
        raise PipelineError(f"cannot load the diffusion model's tokenizer/ or scheduler/ ({type(e).__name__}: {e})",
                            path=folder, fix=f"copy the complete folder: {LAYOUT}") from e
    lc = vae.config.latent_channels
    if unet.config.in_channels != 2 * lc + 1:  # noisy latent, mask, masked-image latent
        raise PipelineError(f"the UNet's in_channels ({unet.config.in_channels}) does not match an inpainting "
                            f"UNet for this VAE ({lc} + 1 + {lc})", path=folder / "unet",
                            fix="use Stable Diffusion INPAINTING weights whose components belong together")
    return DiffusionModel(folder, unet, vae, text_encoder, tokenizer, scheduler)


# --------------------------------------------------------------------------------------------------
# inpainting conditioned on the SBM fill


@dataclass
class DiffusionParams:
    """Parameters of :func:`refine_fill`."""

    prompt: str = ""  # text condition; "" = unconditional (the masked image carries the context)
    negative_prompt: str = ""
    strength: float = 0.5  # how far the SBM init is noised: 1 = from scratch, 0 = unchanged
    steps: int = 20  # DDIM schedule length; int(steps * strength) denoising steps run
    guidance: float = 1.0  # classifier-free guidance; 1 = off (one UNet pass per step)
    resolution: int = 512  # the crop around the hole is resized so its longer side is this
    context: float = 0.5  # the crop is the hole's bounding box grown by this fraction per side
    blend: str = "poisson"  # "poisson": seamless at the hole's rim; "paste": the decoded pixels as they are
    seed: int = 0

    def validate(self) -> None:
        if not 0.0 < self.strength <= 1.0:
            raise PipelineError(f"diffusion strength must be in (0, 1] (got {self.strength})",
                                fix="use e.g. 0.5: below 1 the SBM fill is refined, not replaced")
        if self.steps < 1:
            raise PipelineError(f"diffusion steps must be >= 1 (got {self.steps})", fix="use e.g. 20")
        if self.resolution < 8:
            raise PipelineError(f"diffusion resolution must be >= 8 (got {self.resolution})", fix="use 512")
        if self.blend not in ("poisson", "paste"):
            raise PipelineError(f"unknown diffusion blend {self.blend!r}", fix="use poisson or paste")


def hole_crop(region: np.ndarray, context: float, min_margin: int = 8) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1): the bounding box of ``region`` grown by ``context`` x its size per side
    (at least ``min_margin`` pixels), clipped to the image."""
    ys, xs = np.nonzero(region)
    h, w = region.shape
    y0, y1, x0, x1 = int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1
    my = max(min_margin, int(round(context * (y1 - y0))))
    mx = max(min_margin, int(round(context * (x1 - x0))))
    return max(0, y0 - my), min(h, y1 + my), max(0, x0 - mx), min(w, x1 + mx)


def work_size(h: int, w: int, longest: int, multiple: int) -> tuple[int, int]:
    """(height, width) with the longer side about ``longest``, aspect kept, both multiples of ``multiple``."""
    s = longest / max(h, w)
    return (max(multiple, int(round(h * s / multiple)) * multiple),
            max(multiple, int(round(w * s / multiple)) * multiple))


def refine_fill(model: DiffusionModel, image: np.ndarray, region: np.ndarray, params: DiffusionParams,
                seed: int | None = None) -> np.ndarray:
    """Refine the fill of ``region`` in ``image`` (HxWx3 float32 in [0,1], already completed by SBM)
    with the inpainting model: img2img from the SBM fill at ``strength``, the rest of the crop as the
    masked-image condition. Returns a new image; pixels outside ``region`` are unchanged."""
    import cv2

    from .sbm import poisson_blend

    params.validate()
    img = np.asarray(image, np.float32)
    region = np.asarray(region, bool)
    out = img.copy()
    if not region.any():
        return out
    y0, y1, x0, x1 = hole_crop(region, params.context)
    crop, creg = img[y0:y1, x0:x1], region[y0:y1, x0:x1]
    H, W = work_size(y1 - y0, x1 - x0, params.resolution, model.multiple)
    x = torch.from_numpy(cv2.resize(crop, (W, H), interpolation=cv2.INTER_AREA if H < crop.shape[0]
                                    else cv2.INTER_CUBIC)).clamp(0, 1).permute(2, 0, 1)[None].contiguous()
    # any hole pixel touching a work pixel makes it masked (the resized mask must cover the hole)
    m = cv2.resize(creg.astype(np.float32), (W, H), interpolation=cv2.INTER_AREA if H < crop.shape[0]
                   else cv2.INTER_LINEAR) > 0
    mask = torch.from_numpy(m.astype(np.float32))[None, None]
    gen = torch.Generator().manual_seed(params.seed if seed is None else seed)
    sched = model.scheduler
    with torch.no_grad():
        init = model.encode(x)
        mask_lat, masked_lat = model.condition(x, mask)
        cond = model.text_embeddings(params.prompt)
        uncond = model.text_embeddings(params.negative_prompt) if params.guidance != 1.0 else None
        sched.set_timesteps(params.steps)
        n_run = max(1, min(params.steps, int(params.steps * params.strength)))
        timesteps = sched.timesteps[params.steps - n_run:]
        noise = torch.randn(init.shape, generator=gen)
        lat = sched.add_noise(init, noise, timesteps[:1])  # the SBM fill, partly noised: img2img
        for t in timesteps:
            eps = model.predict_noise(sched.scale_model_input(lat, t), t, mask_lat, masked_lat, cond, uncond,
                                      params.guidance)
            lat = sched.step(eps, t, lat, generator=gen).prev_sample
        dec = model.decode(lat)[0].permute(1, 2, 0).numpy()
    if not np.isfinite(dec).all():
        raise PipelineError("the diffusion model produced non-finite pixels", path=model.folder,
                            fix="check the weights (a float16-only checkpoint?) or use backend = sbm")
    back = cv2.resize(dec, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA if H > crop.shape[0]
                      else cv2.INTER_CUBIC)
    # the guide is the decoded crop everywhere in the crop: its gradients across the rim (not the
    # jump from the known pixels to it) drive the Poisson solve, so the fill meets the rim without a seam
    guide = img.copy()
    guide[y0:y1, x0:x1] = np.clip(back, 0.0, 1.0)
    if params.blend == "poisson":
        out = poisson_blend(img, guide, region)
    else:
        out[region] = guide[region]
    out[~region] = img[~region]  # exactly unchanged outside, whatever the solver did
    return out.astype(np.float32)


# --------------------------------------------------------------------------------------------------
# score distillation sampling


@dataclass
class SDSParams:
    """Parameters of :func:`sds_loss`."""

    prompt: str = ""
    negative_prompt: str = ""
    guidance: float = 1.0  # classifier-free guidance (1 = off: one UNet pass)
    min_t: float = 0.02  # timesteps drawn uniformly in [min_t, max_t] x the training steps; low
    max_t: float = 0.5  # noise levels refine what the render shows rather than replace it


def sds_loss(model: DiffusionModel, render: torch.Tensor, hole: torch.Tensor, params: SDSParams,
             generator: torch.Generator, embeddings: tuple[torch.Tensor, torch.Tensor | None] | None = None
             ) -> torch.Tensor:
    """Score Distillation Sampling on a render of the hole region.

    ``render``: [H,W,3] (the rasterizer's layout) in [0,1], differentiable; ``hole``: [H,W] bool, the
    pixels the prior may change. Its sides are resized (bilinear, differentiable) to multiples of
    :attr:`DiffusionModel.multiple`. Returns a scalar whose gradient with respect to the render's
    latent is ``w(t) (eps_pred - eps)`` inside the hole (mean over the hole's latent elements),
    ``w(t) = 1 - alpha_bar(t)``; the UNet runs without gradient, the VAE encoder with it.
    """
    if not bool(hole.any()):
        return render.sum() * 0.0
    H, W = render.shape[:2]
    mult = model.multiple
    h2, w2 = max(mult, round(H / mult) * mult), max(mult, round(W / mult) * mult)
    x = render.permute(2, 0, 1)[None].clamp(0.0, 1.0)
    m = hole.to(torch.float32)[None, None]
    if (h2, w2) != (H, W):
        x = F.interpolate(x, size=(h2, w2), mode="bilinear", align_corners=False)
        m = (F.interpolate(m, size=(h2, w2), mode="bilinear", align_corners=False) > 0).float()
    lat = model.encode(x)
    mask_lat, masked_lat = model.condition(x.detach(), m)
    sched = model.scheduler
    T = sched.config.num_train_timesteps
    lo = int(params.min_t * T)
    hi = max(lo + 1, int(params.max_t * T))
    t = torch.randint(lo, hi, (1,), generator=generator)
    noise = torch.randn(lat.shape, generator=generator)
    noisy = sched.add_noise(lat.detach(), noise, t)
    if embeddings is None:
        cond = model.text_embeddings(params.prompt)
        uncond = model.text_embeddings(params.negative_prompt) if params.guidance != 1.0 else None
    else:
        cond, uncond = embeddings
    eps = model.predict_noise(noisy, t, mask_lat, masked_lat, cond, uncond, params.guidance)
    w = 1.0 - sched.alphas_cumprod[t].to(lat.dtype)
    # only the hole is distilled (dilated by one latent cell: the rim's latents mix both sides)
    region = (F.max_pool2d(mask_lat, 3, stride=1, padding=1) > 0).to(lat.dtype)
    grad = torch.nan_to_num(w * (eps - noise) * region)
    # surrogate: d(loss)/d(lat) = grad / n; normalised per hole latent element so lambda_sds is
    # comparable to the mean photometric loss whatever the crop size
    n = region.sum() * lat.shape[1]
    return (grad.detach() * lat).sum() / n.clamp(min=1.0)
