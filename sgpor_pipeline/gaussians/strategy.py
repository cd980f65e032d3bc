"""Densification strategies under a Gaussian budget (gsplat-style hooks).

A strategy is a small object with a budget ``cap`` (the most Gaussians it may create) and three
hooks the training loop calls every iteration::

    strategy.step_pre_backward(model, optimizers, state, step, info)   # after rendering
    loss.backward(); optimizers step
    strategy.step_post_backward(model, optimizers, state, step, info, lr=means_lr)

``model`` is a :class:`~sgpor_pipeline.gaussians.model.GaussianModel`, ``optimizers`` a dict of one
``torch.optim.Adam`` per parameter name (so the Adam moments follow every change of the Gaussian
set), ``state`` the strategy's own tensors (from :meth:`initialize_state`; checkpointed by the
trainer), ``info`` the rasterizer's meta (``means2d`` with its ``.grad``, ``radii``, ``width``,
``height``, ``n_cameras``) plus ``generator`` (the trainer's seeded ``torch.Generator``).

Two strategies:

``adc`` (:class:`ADCStrategy`)
    The adaptive density control of 3DGS, budgeted: Gaussians whose accumulated screen-space
    position gradient exceeds ``grow_grad2d`` are cloned (small ones) or split in two (large ones);
    when the candidates exceed the room left under ``cap``, the ones with the largest gradients win.
    Transparent (opacity < ``prune_opa``) Gaussians are pruned, and, once opacities are reset (every
    ``reset_every`` steps, off by default for short runs), oversized ones (largest axis >
    ``prune_scale3d`` x scene extent) too.
``mcmc`` (:class:`MCMCStrategy`)
    3DGS as MCMC (Kheradmand et al. 2024): every ``refine_every`` steps dead Gaussians (opacity <=
    ``min_opacity``) are relocated onto live ones sampled by opacity (opacity and scale adjusted so
    the rendered density is preserved), and the count grows by ``grow_rate`` towards ``cap``; every
    step the positions get noise scaled by the covariance and by how transparent the Gaussian is.
    Adds ``opacity_reg`` and ``scale_reg`` terms to the loss (:meth:`extra_loss`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from .model import GaussianModel

STRATEGIES = ("adc", "mcmc")


# --------------------------------------------------------------------------------------------------
# parameter surgery that keeps the Adam moments aligned


def _replace_params(model: GaussianModel, optimizers: dict[str, torch.optim.Optimizer],
                    param_fn: Callable[[str, torch.Tensor], torch.Tensor],
                    state_fn: Callable[[str, torch.Tensor], torch.Tensor],
                    names: tuple[str, ...] | None = None) -> None:
    """Replace each parameter ``p`` by ``param_fn(name, p)`` and each per-Gaussian optimizer state
    tensor ``v`` (Adam's exp_avg / exp_avg_sq) by ``state_fn(name, v)``."""
    for name in names or tuple(model.params):
        old = model.params[name]
        new = torch.nn.Parameter(param_fn(name, old.detach()), requires_grad=old.requires_grad)
        opt = optimizers.get(name)
        if opt is not None:
            group = opt.param_groups[0]
            st = opt.state.pop(old, {})
            for key, v in list(st.items()):
                if isinstance(v, torch.Tensor) and v.dim() > 0 and v.shape[0] == old.shape[0]:
                    st[key] = state_fn(name, v)
            group["params"][0] = new
            if st:
                opt.state[new] = st
        model.params[name] = new


def remove(model: GaussianModel, optimizers: dict, mask: torch.Tensor) -> None:
    """Delete the Gaussians where ``mask`` is True."""
    keep = ~mask
    _replace_params(model, optimizers, lambda n, p: p[keep], lambda n, v: v[keep])


def duplicate(model: GaussianModel, optimizers: dict, mask: torch.Tensor) -> None:
    """Append a copy of the Gaussians where ``mask`` is True (the copies start with zero moments)."""
    sel = torch.nonzero(mask).squeeze(1)
    _replace_params(model, optimizers, lambda n, p: torch.cat([p, p[sel]]),
                    lambda n, v: torch.cat([v, torch.zeros_like(v[sel])]))


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=-1).reshape(q.shape[:-1] + (3, 3))


def split(model: GaussianModel, optimizers: dict, mask: torch.Tensor, generator: torch.Generator) -> None:
    """Replace each Gaussian where ``mask`` is True by two samples drawn from it, 1.6x smaller (3DGS)."""
    sel = torch.nonzero(mask).squeeze(1)
    rest = torch.nonzero(~mask).squeeze(1)
    p = model.params
    scales = torch.exp(p["scales"].detach()[sel])
    R = quat_to_rotmat(p["quats"].detach()[sel])
    # drawn on the CPU (the trainer's generator) whatever the device: the same seed, the same samples
    noise = torch.randn(2, len(sel), 3, generator=generator, dtype=scales.dtype).to(scales.device)
    samples = torch.einsum("nij,bnj->bni", R, scales[None] * noise)  # [2,S,3]

    def param_fn(name: str, x: torch.Tensor) -> torch.Tensor:
        if name == "means":
            new = (x[sel][None] + samples).reshape(-1, 3)
        elif name == "scales":
            new = torch.log(scales / 1.6).repeat(2, 1)
        else:
            new = x[sel].repeat((2,) + (1,) * (x.dim() - 1))
        return torch.cat([x[rest], new])

    def state_fn(name: str, v: torch.Tensor) -> torch.Tensor:
        return torch.cat([v[rest], v.new_zeros((2 * len(sel),) + v.shape[1:])])

    _replace_params(model, optimizers, param_fn, state_fn)


def reset_opacity(model: GaussianModel, optimizers: dict, value: float) -> None:
    """Clamp every opacity to at most ``value`` (and zero its Adam moments)."""
    logit = math.log(value / (1 - value))
    _replace_params(model, optimizers, lambda n, p: torch.clamp_max(p, logit), lambda n, v: torch.zeros_like(v),
                    names=("opacities",))


# --------------------------------------------------------------------------------------------------
# strategies


class Strategy:
    """Base class: a budget and the two hooks (see the module docstring)."""

    name = ""

    def __init__(self, cap: int):
        self.cap = int(cap)

    def initialize_state(self, model: GaussianModel, scene_extent: float) -> dict[str, Any]:
        return {"scene_extent": float(scene_extent)}

    def init_opacity(self) -> float:
        """Opacity new Gaussians start with when initialised from points."""
        return 0.1

    def extra_loss(self, model: GaussianModel, step: int) -> torch.Tensor | None:
        return None

    def grad_mask(self, state: dict) -> torch.Tensor | None:
        """[N] bool: the Gaussians this strategy trains (the trainer passes it to the rasterizer,
        which then skips the others' gradients); None = all of them."""
        return None

    def step_pre_backward(self, model: GaussianModel, optimizers: dict, state: dict, step: int,
                          info: dict[str, Any]) -> None:
        if "means2d" in info and info["means2d"].requires_grad:
            info["means2d"].retain_grad()

    def step_post_backward(self, model: GaussianModel, optimizers: dict, state: dict, step: int,
                           info: dict[str, Any], lr: float = 0.0) -> dict[str, int] | None:
        """Returns what changed this step (counts by kind) or None."""
        return None

    def is_growing(self, step: int) -> bool:
        """Whether densification may still add Gaussians at ``step``."""
        return False

    def state_to_save(self, state: dict[str, Any]) -> dict[str, Any]:
        return {k: (v.clone() if isinstance(v, torch.Tensor) else v) for k, v in state.items()}


@dataclass
class ADCParams:
    """Budgeted adaptive density control (3DGS defaults, steps compressed for short CPU runs)."""

    refine_start: int = 100  # first densification step
    refine_stop_frac: float = 0.6  # stop densifying after this fraction of the iterations
    refine_every: int = 100
    grow_grad2d: float = 0.0002  # screen-space gradient threshold (3DGS: 0.0002, NDC units)
    grow_scale3d: float = 0.01  # clone below / split above this x scene extent
    prune_opa: float = 0.005
    prune_scale3d: float = 0.1  # prune Gaussians larger than this x scene extent (after the first reset)
    reset_every: int = 0  # opacity reset period (3DGS: 3000); 0 = never (short runs do better without)


class ADCStrategy(Strategy):
    name = "adc"

    def __init__(self, cap: int, iterations: int, params: ADCParams | None = None):
        super().__init__(cap)
        self.p = params or ADCParams()
        self.iterations = int(iterations)
        self.refine_stop = int(self.p.refine_stop_frac * self.iterations)

    def initialize_state(self, model: GaussianModel, scene_extent: float) -> dict[str, Any]:
        n, dev = len(model), model.device
        return {"scene_extent": float(scene_extent), "grad2d": torch.zeros(n, device=dev),
                "count": torch.zeros(n, device=dev)}

    def is_growing(self, step: int) -> bool:
        return step < self.refine_stop

    def step_post_backward(self, model: GaussianModel, optimizers: dict, state: dict, step: int,
                           info: dict[str, Any], lr: float = 0.0) -> dict[str, int] | None:
        if step >= self.refine_stop:
            return None
        means2d = info.get("means2d")
        if means2d is not None and means2d.grad is not None:
            g = means2d.grad.detach().clone()  # [C,N,2]
            g[..., 0] *= info["width"] / 2.0 * info["n_cameras"]
            g[..., 1] *= info["height"] / 2.0 * info["n_cameras"]
            sel = info["radii"] > 0  # [C,N]
            gn = g.norm(dim=-1)
            state["grad2d"] += (gn * sel).sum(0).to(state["grad2d"].dtype)
            state["count"] += sel.sum(0).to(state["count"].dtype)
        if step > self.p.refine_start and step % self.p.refine_every == 0:
            out = self._refine(model, optimizers, state, info["generator"], step)
            if self.p.reset_every > 0 and step % self.p.reset_every == 0:
                reset_opacity(model, optimizers, 2.0 * self.p.prune_opa)
                out["reset"] = 1
            return out
        return None

    def _refine(self, model: GaussianModel, optimizers: dict, state: dict,
                generator: torch.Generator, step: int = 0) -> dict[str, int]:
        ext = state["scene_extent"]
        avg = state["grad2d"] / state["count"].clamp_min(1)
        high = avg > self.p.grow_grad2d
        # state["eligible"] (optional, [N] bool): only these Gaussians densify or are pruned; the mask
        # follows the surgery (copies and split halves of eligible Gaussians are eligible)
        eligible = state.get("eligible")
        if eligible is not None:
            high &= eligible
        max_scale = model.scales_linear().max(dim=-1).values
        small = max_scale <= self.p.grow_scale3d * ext
        cand = torch.nonzero(high).squeeze(1)
        room = max(0, self.cap - len(model))
        if len(cand) > room:  # the budget: keep the largest gradients
            top = torch.topk(avg[cand], room).indices if room > 0 else cand[:0]
            cand = cand[top]
        dev = model.device
        dup = torch.zeros(len(model), dtype=torch.bool, device=dev)
        spl = torch.zeros(len(model), dtype=torch.bool, device=dev)
        dup[cand] = small[cand]
        spl[cand] = ~small[cand]
        n_dup, n_split = int(dup.sum()), int(spl.sum())
        if n_dup:
            duplicate(model, optimizers, dup)
            spl = torch.cat([spl, spl.new_zeros(n_dup)])
            if eligible is not None:
                eligible = torch.cat([eligible, eligible.new_ones(n_dup)])
        if n_split:
            split(model, optimizers, spl, generator)
            if eligible is not None:
                eligible = torch.cat([eligible[~spl], eligible.new_ones(2 * n_split)])
        # prune transparent Gaussians, and oversized ones once opacity resets are active (3DGS/gsplat:
        # only after the first reset; earlier, far background Gaussians are legitimately large)
        op = model.opacities_activated()
        prune = op < self.p.prune_opa
        if self.p.reset_every > 0 and step > self.p.reset_every:
            prune |= model.scales_linear().max(dim=-1).values > self.p.prune_scale3d * ext
        if eligible is not None:
            prune &= eligible
        n_prune = int(prune.sum())
        if n_prune and n_prune < len(model):
            remove(model, optimizers, prune)
            if eligible is not None:
                eligible = eligible[~prune]
        if eligible is not None:
            state["eligible"] = eligible
        n = len(model)
        state["grad2d"] = torch.zeros(n, device=dev)
        state["count"] = torch.zeros(n, device=dev)
        return {"cloned": n_dup, "split": n_split, "pruned": n_prune}


@dataclass
class MCMCParams:
    """3DGS-MCMC (gsplat's MCMCStrategy defaults, steps compressed for short CPU runs)."""

    refine_start: int = 100
    refine_stop_frac: float = 0.8
    refine_every: int = 100
    # Growth per refinement. 3DGS-MCMC uses 1.05 (+5 %), which in a 30k-iteration run reaches the cap; a
    # short CPU run would stop far below it, so 0 (default) = grow geometrically to reach the cap by
    # grow_until_frac of the iterations.
    grow_rate: float = 0.0
    grow_until_frac: float = 0.5
    min_opacity: float = 0.005
    noise_lr: float = 5e5
    opacity_reg: float = 0.01
    scale_reg: float = 0.01
    init_opacity: float = 0.5


class MCMCStrategy(Strategy):
    name = "mcmc"

    def __init__(self, cap: int, iterations: int, params: MCMCParams | None = None):
        super().__init__(cap)
        self.p = params or MCMCParams()
        self.iterations = int(iterations)
        self.refine_stop = int(self.p.refine_stop_frac * self.iterations)
        n_max = 51
        self.binoms = torch.zeros(n_max, n_max)
        for n in range(n_max):
            for k in range(n + 1):
                self.binoms[n, k] = math.comb(n, k)

    def init_opacity(self) -> float:
        return self.p.init_opacity

    def is_growing(self, step: int) -> bool:
        return step < self.refine_stop

    def extra_loss(self, model: GaussianModel, step: int) -> torch.Tensor | None:
        loss = None
        if self.p.opacity_reg > 0:
            loss = self.p.opacity_reg * torch.sigmoid(model.params["opacities"]).mean()
        if self.p.scale_reg > 0:
            s = self.p.scale_reg * torch.exp(model.params["scales"]).mean()
            loss = s if loss is None else loss + s
        return loss

    def step_post_backward(self, model: GaussianModel, optimizers: dict, state: dict, step: int,
                           info: dict[str, Any], lr: float = 0.0) -> dict[str, int] | None:
        gen = info["generator"]
        out = None
        if self.p.refine_start < step < self.refine_stop and step % self.p.refine_every == 0:
            n_reloc = self._relocate(model, optimizers, gen)
            n_add = self._add(model, optimizers, gen, step)
            out = {"relocated": n_reloc, "added": n_add}
        self._inject_noise(model, lr * self.p.noise_lr, gen)
        return out

    # the relocation formula of 3DGS-MCMC (eq. 9): N copies render like the original
    def _relocation(self, opacities: torch.Tensor, scales: torch.Tensor,
                    ratios: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        ratios = ratios.clamp(1, self.binoms.shape[0])
        new_op = 1.0 - torch.pow(1.0 - opacities, 1.0 / ratios.to(opacities.dtype))
        m = int(ratios.max()) if len(ratios) else 1
        dev = opacities.device
        i = torch.arange(1, m + 1, device=dev).view(1, -1, 1)  # i copies; binoms row i - 1
        k = torch.arange(m, device=dev).view(1, 1, -1)
        coef = self.binoms[:m, :m].to(dev)[None] * ((-1.0) ** k) / torch.sqrt(k + 1.0)  # [1,I,K]
        valid = (k < i) & (i <= ratios.view(-1, 1, 1))  # sum over i = 1..ratio, k = 0..i-1
        terms = coef * new_op.view(-1, 1, 1) ** (k + 1)
        denom = torch.where(valid, terms, torch.zeros_like(terms)).sum(dim=(1, 2))
        coeffs = opacities / denom
        new_scales = coeffs[:, None] * scales
        return new_op, new_scales

    def _sample_and_copy(self, model: GaussianModel, optimizers: dict, n: int, gen: torch.Generator,
                         source_pool: torch.Tensor, dest: torch.Tensor | None) -> int:
        """Sample ``n`` sources from ``source_pool`` by opacity; write them into ``dest`` indices (relocate) or
        append them (``dest`` None); the sources' opacity/scale are split between them and their copies."""
        op = model.opacities_activated()
        probs = op[source_pool].clamp_min(1e-12)
        # sampled on the CPU with the trainer's generator (a CUDA sampler would need its own)
        pick = torch.multinomial(probs.cpu(), n, replacement=True, generator=gen).to(probs.device)
        src = source_pool[pick]
        ratios = torch.bincount(src, minlength=len(model))[src] + 1
        new_op, new_scales = self._relocation(op[src], model.scales_linear()[src], ratios)
        new_op = new_op.clamp(self.p.min_opacity, 1.0 - torch.finfo(torch.float32).eps)
        logit = torch.log(new_op / (1 - new_op))
        log_scales = torch.log(new_scales.clamp_min(1e-12))
        with torch.no_grad():
            model.params["opacities"][src] = logit
            model.params["scales"][src] = log_scales
        touched = src if dest is None else torch.cat([src, dest])

        def param_fn(name: str, x: torch.Tensor) -> torch.Tensor:
            if dest is None:
                return torch.cat([x, x[src]])
            x = x.clone()
            x[dest] = x[src]
            return x

        def state_fn(name: str, v: torch.Tensor) -> torch.Tensor:
            v = v.clone()
            v[touched] = 0
            if dest is None:
                v = torch.cat([v, v.new_zeros((n,) + v.shape[1:])])
            return v

        _replace_params(model, optimizers, param_fn, state_fn)
        return n

    def _relocate(self, model: GaussianModel, optimizers: dict, gen: torch.Generator) -> int:
        op = model.opacities_activated()
        dead = op <= self.p.min_opacity
        n_dead = int(dead.sum())
        alive = torch.nonzero(~dead).squeeze(1)
        if n_dead == 0 or len(alive) == 0:
            return 0
        return self._sample_and_copy(model, optimizers, n_dead, gen, alive, torch.nonzero(dead).squeeze(1))

    def growth_rate(self, step: int, n: int) -> float:
        if self.p.grow_rate > 0:
            return self.p.grow_rate
        until = max(self.p.grow_until_frac * self.iterations, step + 1)
        left = max(1, int((until - step) // self.p.refine_every) + 1)  # refinements left, this one included
        return max(1.0, (self.cap / max(n, 1)) ** (1.0 / left))

    def _add(self, model: GaussianModel, optimizers: dict, gen: torch.Generator, step: int = 0) -> int:
        n = len(model)
        target = min(self.cap, int(math.floor(n * self.growth_rate(step, n))))
        n_add = max(0, target - n)
        if n_add == 0:
            return 0
        return self._sample_and_copy(model, optimizers, n_add, gen, torch.arange(n, device=model.device), None)

    def _inject_noise(self, model: GaussianModel, scaler: float, gen: torch.Generator) -> None:
        if scaler <= 0:
            return
        p = model.params
        op = torch.sigmoid(p["opacities"].detach())
        scales = torch.exp(p["scales"].detach())
        R = quat_to_rotmat(p["quats"].detach())
        M = R * scales[:, None, :]
        cov = M @ M.transpose(-1, -2)
        noise = torch.randn(p["means"].shape, generator=gen, dtype=p["means"].dtype).to(p["means"].device)
        gate = 1.0 / (1.0 + torch.exp(-100.0 * ((1.0 - op) - 0.995)))
        noise = torch.einsum("nij,nj->ni", cov, noise * gate[:, None]) * scaler
        with torch.no_grad():
            p["means"].add_(noise)


def make_strategy(name: str, cap: int, iterations: int, grow_grad2d: float | None = None,
                  refine_stop_frac: float | None = None) -> Strategy:
    """A strategy by name ("adc" or "mcmc") with its default parameters, optionally overriding the
    densification gradient threshold (adc) and the fraction of the iterations that densify (both)."""
    if name == "adc":
        ap = ADCParams()
        if grow_grad2d is not None:
            ap.grow_grad2d = grow_grad2d
        if refine_stop_frac is not None:
            ap.refine_stop_frac = refine_stop_frac
        return ADCStrategy(cap, iterations, ap)
    if name == "mcmc":
        mp = MCMCParams()
        if refine_stop_frac is not None:
            mp.refine_stop_frac = refine_stop_frac
        return MCMCStrategy(cap, iterations, mp)
    raise ValueError(f"unknown densification strategy {name!r}; choose one of {STRATEGIES}")
