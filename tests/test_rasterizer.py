"""The Gaussian rasterizer: cpu kernel against the torch reference, gradients, hard cases.

Scenes are small so that the dense torch reference stays fast; the whole file runs in well under
a minute on 2 cores.
"""

from __future__ import annotations

import math
import os
import warnings

import pytest
import torch

from sgpor_pipeline.errors import NonFiniteError
from sgpor_pipeline.gaussians import _raster_common as rcommon
from sgpor_pipeline.gaussians import _raster_cpu
from sgpor_pipeline.gaussians._raster_scenes import look_at_camera, random_scene
from sgpor_pipeline.gaussians.rasterizer import (
    NonFiniteInputError,
    RasterizerInputError,
    count_non_finite,
    cpu_kernel_available,
    first_non_finite,
    rasterization,
)

PARAMS = ("means", "quats", "scales", "opacities", "colors")

@pytest.fixture(autouse=True)
def _torch_single_thread():
    """These scenes are tiny: torch's intra-op threads only add fork/join costs (large ones on a
    busy machine). The kernel's own thread count is a separate argument (num_threads)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


requires_kernel = pytest.mark.skipif(not cpu_kernel_available(),
                                     reason=f"cpu kernel not built: {_raster_cpu.load_error()}")


def test_kernel_is_built():
    """The install must build the C++ kernel (a missing kernel silently costs 30x speed)."""
    assert cpu_kernel_available(), _raster_cpu.load_error()


def _leaf(scene: dict, extra: dict | None = None) -> dict:
    out = {}
    for k, v in scene.items():
        out[k] = v.detach().clone().requires_grad_(True) if k in PARAMS and v is not None else v
    if extra:
        out.update(extra)
    return out


def run(scene: dict, backend: str, seed: int = 0, **kw) -> dict:
    """Renders, backpropagates fixed random weights; returns outputs and gradients."""
    args = _leaf(scene)
    bg = kw.pop("backgrounds", None)
    if bg is not None:
        bg = bg.detach().clone().requires_grad_(True)
        kw["backgrounds"] = bg
    render, alpha, meta = rasterization(**args, backend=backend, **kw)
    meta["means2d"].retain_grad()
    g = torch.Generator().manual_seed(seed)
    w_r = torch.randn(render.shape, generator=g, dtype=torch.float64).to(render)  # dtype and device
    w_a = torch.randn(alpha.shape, generator=g, dtype=torch.float64).to(alpha)
    loss = (render * w_r).sum() + (alpha * w_a).sum()
    loss.backward()
    out = {"render": render.detach(), "alpha": alpha.detach(), "contrib": meta["contrib"],
           "radii": meta["radii"], "depths": meta["depths"].detach(),
           "means2d": meta["means2d"].detach(), "conics": meta["conics"].detach(),
           "g_means2d": meta["means2d"].grad, "backend": meta["backend"]}
    for k in PARAMS:
        if args.get(k) is not None:
            out["g_" + k] = args[k].grad
    if bg is not None:
        out["g_backgrounds"] = bg.grad
    return out


def assert_close(a: dict, b: dict, rtol: float, atol: float, skip=("backend",)) -> None:
    for k in a:
        if k in skip:
            continue
        x, y = a[k], b[k]
        if x is None or y is None:
            assert x is None and y is None, k
            continue
        assert x.shape == y.shape, (k, x.shape, y.shape)
        if not x.is_floating_point():
            assert torch.equal(x, y), k
            continue
        assert torch.isfinite(x).all(), k
        scale = max(1.0, float(y.abs().max())) if y.numel() else 1.0
        err = float((x.double() - y.double()).abs().max()) if x.numel() else 0.0
        assert err <= atol + rtol * scale, f"{k}: max error {err:.3e} (scale {scale:.3e})"


def assert_bitwise(a: dict, b: dict, skip=("backend",)) -> None:
    for k in a:
        if k in skip or a[k] is None:
            continue
        assert torch.equal(a[k], b[k]), k


# ------------------------------------------------------------------------------------------------
# cpu kernel == torch reference


@requires_kernel
@pytest.mark.parametrize("mode", ["RGB", "D", "ED", "RGB+D", "RGB+ED"])
@pytest.mark.parametrize("sh_degree", [None, 0, 1, 2, 3])
def test_cpu_matches_torch_double(mode, sh_degree):
    scene = random_scene(150, 37, 29, seed=3 + (sh_degree or 0), dtype=torch.float64, sigma_px=2.5,
                         sh_degree=sh_degree)
    kw = {"render_mode": mode}
    if mode.startswith("RGB"):
        kw["backgrounds"] = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    ref = run(scene, "torch", **dict(kw))
    cpu = run(scene, "cpu", **dict(kw))
    assert cpu["backend"] == "cpu" and ref["backend"] == "torch"
    assert ref["alpha"].max() > 0.99  # the scene saturates: the T cut-off is exercised
    assert_close(cpu, ref, rtol=1e-10, atol=1e-10)


@requires_kernel
@pytest.mark.parametrize("tile_size", [8, 16])
def test_cpu_matches_torch_float32_two_cameras(tile_size):
    scene = random_scene(300, 48, 32, seed=11, sigma_px=2.0, sh_degree=3)
    # a second camera, rotated and shifted, so that per-camera sums and SH directions matter
    ang = 0.2
    R = torch.tensor([[math.cos(ang), 0, math.sin(ang)], [0, 1, 0], [-math.sin(ang), 0, math.cos(ang)]])
    vm2 = torch.eye(4)
    vm2[:3, :3] = R
    vm2[:3, 3] = torch.tensor([0.3, -0.1, 0.5])
    scene["viewmats"] = torch.cat([scene["viewmats"], vm2[None]])
    scene["Ks"] = scene["Ks"].expand(2, -1, -1).clone()
    kw = {"render_mode": "RGB+ED", "tile_size": tile_size,
          "backgrounds": torch.tensor([[0.1, 0.2, 0.3], [1.0, 0.0, 0.5]])}
    ref = run(scene, "torch", **dict(kw))
    cpu = run(scene, "cpu", **dict(kw))
    assert_close(cpu, ref, rtol=2e-4, atol=2e-5)


@requires_kernel
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("tile_size", [8, 16])
def test_thin_tilted_gaussians_match_the_dense_reference(dtype, tile_size):
    """Needles: one axis 4-25 px long, the others 0.02-0.4 px, at random angles. Their bounding boxes
    hold many tile rows (and whole tiles) that no pixel of the footprint reaches, which the kernel
    skips (``trim_rows``); the torch reference evaluates every pixel, so a row skipped wrongly (a pixel
    at the footprint's edge, alpha near 1/255) shows here."""
    scene = random_scene(400, 64, 48, seed=21, dtype=dtype, opacity_range=(0.02, 0.99))
    g = torch.Generator().manual_seed(5)
    n = scene["means"].shape[0]
    z = scene["means"][:, 2:3].double()
    fx = float(scene["Ks"][0, 0, 0])
    px = torch.stack([4 + 21 * torch.rand(n, generator=g, dtype=torch.float64),
                      0.02 + 0.38 * torch.rand(n, generator=g, dtype=torch.float64),
                      0.02 + 0.38 * torch.rand(n, generator=g, dtype=torch.float64)], -1)
    scene["scales"] = (px * z / fx).to(dtype)
    kw = {"render_mode": "RGB+ED", "tile_size": tile_size}
    ref = run(scene, "torch", **dict(kw))
    cpu = run(scene, "cpu", **dict(kw))
    if dtype == torch.float64:
        assert_close(cpu, ref, rtol=1e-10, atol=1e-10)
    else:
        assert_close(cpu, ref, rtol=2e-4, atol=2e-5)


@requires_kernel
def test_cpu_matches_torch_features_per_camera_and_many_channels():
    scene = random_scene(120, 30, 20, seed=5, dtype=torch.float64, sigma_px=2.5)
    g = torch.Generator().manual_seed(0)
    scene["colors"] = torch.rand(1, 120, 6, generator=g, dtype=torch.float64)  # [C,N,6]: two passes
    ref = run(scene, "torch", render_mode="RGB+D")
    cpu = run(scene, "cpu", render_mode="RGB+D")
    assert cpu["render"].shape == (1, 20, 30, 7)
    assert_close(cpu, ref, rtol=1e-10, atol=1e-10)
    scene["colors"] = torch.rand(120, 1, generator=g, dtype=torch.float64)  # one channel
    assert_close(run(scene, "cpu"), run(scene, "torch"), rtol=1e-10, atol=1e-10)


def test_torch_reference_blocks_equal_dense():
    """Culling Gaussians per pixel block cannot change the torch reference's result."""
    scene = random_scene(80, 23, 17, seed=2, dtype=torch.float64, sigma_px=2.0, sh_degree=1)
    dense = run(scene, "torch", torch_block=None, render_mode="RGB+D")
    for block in (4, 7):
        assert_close(run(scene, "torch", torch_block=block, render_mode="RGB+D"), dense,
                     rtol=1e-12, atol=1e-12)


def test_single_gaussian_closed_form():
    """One isotropic Gaussian: alpha = o exp(-0.5 d^2 / (s^2 f^2/z^2 + 0.3)) at each pixel centre."""
    W, H = 9, 7
    vm, K = look_at_camera(W, H, dtype=torch.float64)
    f = float(K[0, 0, 0])
    z, s, o = 3.0, 0.02, 0.7
    kw = dict(means=torch.tensor([[0.0, 0.0, z]], dtype=torch.float64),
              quats=torch.tensor([[0.3, 0.0, 0.0, 0.0]], dtype=torch.float64),
              scales=torch.full((1, 3), s, dtype=torch.float64),
              opacities=torch.tensor([o], dtype=torch.float64),
              colors=torch.tensor([[1.0, 0.5, 0.25]], dtype=torch.float64),
              viewmats=vm, Ks=K, width=W, height=H)
    var = (s * f / z) ** 2 + 0.3
    jj, ii = torch.meshgrid(torch.arange(W, dtype=torch.float64), torch.arange(H, dtype=torch.float64),
                            indexing="xy")
    d2 = (jj + 0.5 - W / 2) ** 2 + (ii + 0.5 - H / 2) ** 2
    sigma = 0.5 * d2 / var
    alpha = o * torch.exp(-sigma)
    alpha = torch.where((alpha >= 1 / 255) & (sigma <= math.log(255 * o)), alpha, 0.0)
    for backend in ("torch", "cpu") if cpu_kernel_available() else ("torch",):
        render, acc, meta = rasterization(**kw, backend=backend)
        torch.testing.assert_close(acc[0, ..., 0], alpha, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(render[0, ..., 1], 0.5 * alpha, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(meta["means2d"][0, 0], torch.tensor([W / 2, H / 2], dtype=torch.float64))
        assert int(meta["radii"][0, 0]) == math.ceil(math.sqrt(2 * math.log(255 * o) * var))
        torch.testing.assert_close(meta["contrib"][0, 0], alpha.sum())


def test_median_depth_is_where_the_transmittance_crosses_one_half():
    """Two wide Gaussians on the optical axis, opacity 0.3 at z = 2 and 0.9 at z = 4: at the centre
    the transmittance is 0.7 after the first, 0.07 after the second, so the median depth is 4 while
    the expected depth is (0.3 * 2 + 0.63 * 4) / 0.93; where the total alpha stays below 0.5 the
    median is 0."""
    W, H = 16, 12
    vm, K = look_at_camera(W, H, dtype=torch.float64)
    kw = dict(means=torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 4.0]], dtype=torch.float64),
              quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2, dtype=torch.float64),
              scales=torch.tensor([[0.5] * 3, [0.3] * 3], dtype=torch.float64),
              opacities=torch.tensor([0.3, 0.9], dtype=torch.float64), colors=None, viewmats=vm, Ks=K,
              width=W, height=H)
    backends = ("torch", "cpu") if cpu_kernel_available() else ("torch",)
    for backend in backends:
        md, alpha, meta = rasterization(**kw, render_mode="MD", backend=backend)
        ed, alpha_ed, _ = rasterization(**kw, render_mode="ED", backend=backend)
        assert md.shape == (1, H, W, 1) and meta["backend"] == backend
        torch.testing.assert_close(alpha, alpha_ed, rtol=0, atol=0)
        c = md[0, H // 2, W // 2, 0]
        assert float(c) == 4.0
        assert 3.2 < float(ed[0, H // 2, W // 2, 0]) < 3.5  # (0.3 * 2 + 0.63 * 4) / 0.93 = 3.35, in front
        low = alpha[0, ..., 0] < 0.5
        assert low.any() and (md[0, ..., 0][low] == 0).all()
        assert ((md[0, ..., 0][~low] == 2.0) | (md[0, ..., 0][~low] == 4.0)).all()


@pytest.mark.skipif(not cpu_kernel_available(), reason="needs the cpu kernel")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_median_depth_cpu_matches_torch(dtype):
    scene = random_scene(600, 48, 40, seed=11, sigma_px=2.5, dtype=dtype, opacity_range=(0.2, 0.99))
    scene["colors"] = None
    mask = torch.zeros(1, 40, 48, dtype=torch.bool)
    mask[:, 5:25, 10:40] = True
    ref = rasterization(**scene, render_mode="MD", backend="torch", contribution_mask=mask)
    out = rasterization(**scene, render_mode="MD", backend="cpu", contribution_mask=mask, num_threads=2)
    md_ref, md = ref[0][0, ..., 0], out[0][0, ..., 0]
    assert (md_ref > 0).float().mean() > 0.5  # most pixels cross 0.5
    # the crossing Gaussian is the same one except where T lands on 0.5 within rounding
    same = torch.isclose(md, md_ref, rtol=1e-6, atol=0)
    assert same.float().mean() > (0.999 if dtype == torch.float64 else 0.99)
    torch.testing.assert_close(out[1], ref[1], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(out[2]["contrib"], ref[2]["contrib"], rtol=1e-4, atol=1e-4)
    # a scene lies on the surfaces the median picks: every value is one of the Gaussians' depths
    depths = ref[2]["depths"][0]
    hit = md[md > 0]
    assert torch.isin(hit, depths).all()
    assert not md.requires_grad


# ------------------------------------------------------------------------------------------------
# gradcheck


def _gradcheck_scene(sh_degree):
    """Three large, translucent Gaussians: every pixel is inside every footprint, no alpha clamp,
    no T cut-off, no frustum clamp: the rendering is smooth in all parameters."""
    W, H = 8, 6
    vm, K = look_at_camera(W, H, dtype=torch.float64)
    g = torch.Generator().manual_seed(7)
    means = torch.tensor([[0.05, -0.03, 2.0], [-0.1, 0.05, 2.5], [0.02, 0.08, 3.0]], dtype=torch.float64)
    quats = torch.randn(3, 4, generator=g, dtype=torch.float64)
    scales = torch.tensor([[0.6, 0.4, 0.5], [0.5, 0.7, 0.3], [0.8, 0.6, 0.9]], dtype=torch.float64)
    opacities = torch.tensor([0.35, 0.5, 0.6], dtype=torch.float64)
    if sh_degree is None:
        colors = torch.rand(3, 3, generator=g, dtype=torch.float64)
    else:
        colors = 0.2 * torch.randn(3, (sh_degree + 1) ** 2, 3, generator=g, dtype=torch.float64)
        colors[:, 0] += 1.0
    return means, quats, scales, opacities, colors, vm, K, W, H


@pytest.mark.parametrize("backend", ["cpu", "torch"])
@pytest.mark.parametrize("sh_degree", [None, 3])
def test_gradcheck(backend, sh_degree):
    if backend == "cpu" and not cpu_kernel_available():
        pytest.skip("cpu kernel not built")
    means, quats, scales, opacities, colors, vm, K, W, H = _gradcheck_scene(sh_degree)
    bg = torch.tensor([0.3, 0.6, 0.1], dtype=torch.float64)

    def f(means, quats, scales, opacities, colors, bg):
        render, alpha, meta = rasterization(means, quats, scales, opacities, colors, vm, K, W, H,
                                            sh_degree=sh_degree, backgrounds=bg,
                                            render_mode="RGB+ED", backend=backend)
        return render, alpha, meta["means2d"]

    inputs = [t.clone().requires_grad_(True) for t in (means, quats, scales, opacities, colors, bg)]
    # the full Jacobian for our kernel; a random projection of it for the (slow) dense reference
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-5,
                                    fast_mode=backend == "torch")


# ------------------------------------------------------------------------------------------------
# invariances and determinism


def _tiled_scene():
    return random_scene(2000, 96, 64, seed=21, sigma_px=2.0, sh_degree=1)


@requires_kernel
def test_tile_size_does_not_change_the_image():
    scene = _tiled_scene()
    a = run(scene, "cpu", tile_size=8, render_mode="RGB+D")
    b = run(scene, "cpu", tile_size=16, render_mode="RGB+D")
    for k in ("render", "alpha", "radii", "means2d", "depths", "conics"):
        assert torch.equal(a[k], b[k]), k
    assert_close(a, b, rtol=1e-5, atol=1e-5)


@requires_kernel
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_bitwise_identical_across_thread_counts(dtype):
    scene = random_scene(2000, 96, 64, seed=21, sigma_px=2.0, sh_degree=2, dtype=dtype)
    one = run(scene, "cpu", num_threads=1, render_mode="RGB+D")
    two = run(scene, "cpu", num_threads=2, render_mode="RGB+D")
    four = run(scene, "cpu", num_threads=4, render_mode="RGB+D")
    assert_bitwise(one, two)
    assert_bitwise(one, four)


def _level_probe(path: str) -> None:
    """Everything the kernel computes, with the variant the environment selects (``SGPOR_KERNEL``):
    renders and gradients for both tile sizes (also with a gradient mask, and the median depth), the
    fused SSIM and its gradient, the masked SSD; saves it all (run in a subprocess)."""
    import numpy as np

    torch.set_num_threads(1)
    out = {"kernel": _raster_cpu.kernel_name()}
    scene = random_scene(2000, 96, 64, seed=21, sigma_px=2.0, sh_degree=2)
    for tile in (8, 16):
        res = run(scene, "cpu", tile_size=tile, render_mode="RGB+D")
        out.update({f"{k}_{tile}": v for k, v in res.items() if k != "backend" and v is not None})
        res = run(scene, "cpu", tile_size=tile, render_mode="RGB", grad_mask=torch.arange(2000) % 4 == 0)
        out.update({f"masked_{k}_{tile}": v for k, v in res.items() if k != "backend" and v is not None})
        with torch.no_grad():
            median, alpha, meta = rasterization(**scene, backend="cpu", render_mode="MD", tile_size=tile)
        out.update({f"median_{tile}": median, f"median_contrib_{tile}": meta["contrib"]})
    g = torch.Generator().manual_seed(4)
    x, y = torch.rand(2, 3, 48, 64, generator=g)
    y = (0.7 * x + 0.3 * y).contiguous()
    total, mom = _raster_cpu.ssim_forward(x, y, None, 1)
    out["ssim"] = torch.tensor(total)
    out["ssim_grad"] = _raster_cpu.ssim_backward(x, y, mom, None, 0.5, 1)
    rng = np.random.default_rng(3)
    views = [rng.random((50, 60, 3), dtype=np.float32) for _ in range(2)]
    cand = np.stack([rng.integers(0, 2, (5, 3)), rng.integers(0, 50 - 21 - 6, (5, 3)),
                     rng.integers(0, 60 - 21 - 6, (5, 3))], axis=-1)
    out["ssd"] = torch.from_numpy(_raster_cpu.masked_ssd(
        rng.random((40, 40, 3), dtype=np.float32), rng.random((40, 40), dtype=np.float32),
        rng.integers(0, 40 - 21, (5, 2)), 21, views, cand, 3, threads=1))
    torch.save(out, path)


@requires_kernel
def test_bitwise_identical_across_fma_build_levels(tmp_path):
    """The x86-64 builds with FMA (v3: AVX2, v4: AVX-512) give the same bits: a tile row's lanes
    are summed in a fixed tree, not in the order of the vector width, and the only multiply-adds
    that fuse are the kernel's written-out fmadd() (with gcc choosing, the two builds fused
    different products after an unrelated change). Without this, every fit (and every benchmark
    number after it) changed between an AVX2 and an AVX-512 machine. v2 has no FMA, so its
    multiply-adds round differently: close, not equal. Runs every variant this CPU can execute;
    skipped where fewer than two FMA builds can run (our 2-core machine runs only v2 and v3: a
    lent GPU machine's Xeon runs this test)."""
    import subprocess
    import sys
    from pathlib import Path

    usable = _raster_cpu.usable_variants()
    fma = [k for k in usable if k in ("x86_64_v3", "x86_64_v4", "native")]
    if len(fma) < 2:
        pytest.skip(f"fewer than two FMA builds run on this CPU ({usable})")
    results = {}
    for key in usable:
        path = tmp_path / f"{key}.pt"
        code = (f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); "
                f"from test_rasterizer import _level_probe; _level_probe({str(path)!r})")
        env = {**os.environ, "SGPOR_KERNEL": key}
        subprocess.run([sys.executable, "-c", code], env=env, check=True, timeout=300)
        results[key] = torch.load(path)
        assert results[key].pop("kernel") == key
    ref = results[fma[0]]
    for key in fma[1:]:
        assert_bitwise(ref, results[key])
    if "x86_64_v2" in results:
        assert_close(results["x86_64_v2"], ref, rtol=1e-4, atol=1e-4)


@requires_kernel
def test_gaussian_order_does_not_matter():
    scene = _tiled_scene()
    perm = torch.randperm(2000, generator=torch.Generator().manual_seed(0))
    permuted = {k: (v[perm] if k in PARAMS else v) for k, v in scene.items()}
    a = run(scene, "cpu")
    b = run(permuted, "cpu")
    torch.testing.assert_close(a["render"], b["render"], rtol=0, atol=2e-6)
    torch.testing.assert_close(a["alpha"], b["alpha"], rtol=0, atol=2e-6)
    for k in ("g_means", "g_scales", "g_opacities", "g_colors"):
        torch.testing.assert_close(a[k][perm], b[k], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(a["contrib"][:, perm], b["contrib"], rtol=1e-5, atol=1e-5)


# ------------------------------------------------------------------------------------------------
# hard cases (each checked on both backends against each other, outputs and gradients finite)


def _hard_case(name):
    W, H = 24, 18
    vm, K = look_at_camera(W, H, dtype=torch.float64)
    f = float(K[0, 0, 0])
    one = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)

    def gauss(x_px, y_px, z, s_px, o=0.8, quat=None, scale=None):
        means = torch.tensor([[(x_px - W / 2) * z / f, (y_px - H / 2) * z / f, z]], dtype=torch.float64)
        scales = torch.full((1, 3), s_px * abs(z) / f, dtype=torch.float64) if scale is None else scale
        return dict(means=means, quats=one.clone() if quat is None else quat, scales=scales,
                    opacities=torch.tensor([o], dtype=torch.float64))

    def cat(*gs):
        out = {k: torch.cat([g[k] for g in gs]) for k in gs[0]}
        n = out["means"].shape[0]
        out["colors"] = torch.rand(n, 3, generator=torch.Generator().manual_seed(n), dtype=torch.float64)
        return out

    cases = {
        "behind_camera": cat(gauss(12, 9, -2.0, 3.0), gauss(10, 8, 2.0, 2.0)),
        "near_plane": cat(gauss(12, 9, 0.01, 1.0), gauss(12, 9, 0.0099999, 1.0), gauss(5, 5, 0.0101, 1.0)),
        "border_straddling": cat(gauss(0.2, 9, 2.0, 2.5), gauss(23.9, 17.5, 3.0, 3.0), gauss(-2.0, -1.0, 2.0, 2.0),
                                 gauss(12, 18.5, 2.0, 1.5)),
        "covers_image": cat(gauss(12, 9, 2.0, 80.0, o=0.6), gauss(3, 4, 2.5, 2.0)),
        "sub_pixel": cat(gauss(12.3, 9.7, 2.0, 0.01), gauss(5.5, 5.5, 2.0, 0.001, o=1.0)),
        "zero_scale_axis": cat(gauss(12, 9, 2.0, 0, scale=torch.tensor([[0.05, 0.0, 0.02]], dtype=torch.float64)),
                               gauss(6, 6, 2.0, 0, scale=torch.zeros(1, 3, dtype=torch.float64))),
        "zero_quaternion": cat(gauss(12, 9, 2.0, 2.0, quat=torch.zeros(1, 4, dtype=torch.float64)),
                               gauss(8, 9, 2.0, 0, quat=torch.zeros(1, 4, dtype=torch.float64),
                                     scale=torch.tensor([[0.1, 0.01, 0.03]], dtype=torch.float64))),
        "stacked_opaque": cat(*[gauss(12 + 0.01 * i, 9, 2.0 + 0.01 * i, 3.0, o=0.999) for i in range(100)]),
        "far_outside_frustum": cat(gauss(-400, 9, 2.0, 5.0), gauss(12, 900, 0.5, 3.0), gauss(12, 9, 2.0, 2.0)),
        "tiny_opacity": cat(gauss(12, 9, 2.0, 2.0, o=1.0 / 255 - 1e-6), gauss(10, 9, 2.0, 2.0, o=0.0),
                            gauss(14, 9, 2.0, 2.0, o=2.0 / 255)),
    }
    sc = cases[name]
    sc.update(viewmats=vm, Ks=K, width=W, height=H, sh_degree=None)
    return sc


HARD = ["behind_camera", "near_plane", "border_straddling", "covers_image", "sub_pixel",
        "zero_scale_axis", "zero_quaternion", "stacked_opaque", "far_outside_frustum", "tiny_opacity"]


@pytest.mark.parametrize("name", HARD)
def test_hard_cases(name):
    scene = _hard_case(name)
    kw = {"render_mode": "RGB+ED", "backgrounds": torch.tensor([0.5, 0.5, 0.5], dtype=torch.float64)}
    ref = run(scene, "torch", **dict(kw))
    for k, v in ref.items():
        if isinstance(v, torch.Tensor) and v.is_floating_point():
            assert torch.isfinite(v).all(), (name, k)
    if cpu_kernel_available():
        cpu = run(scene, "cpu", **dict(kw))
        assert_close(cpu, ref, rtol=1e-10, atol=1e-10)
    radii = ref["radii"][0]
    if name == "behind_camera":
        assert radii[0] == 0 and radii[1] > 0
    if name == "near_plane":
        assert radii[0] > 0 and radii[1] == 0 and radii[2] > 0
    if name == "covers_image":
        assert (ref["alpha"] > 0.5).all()
    if name == "stacked_opaque":
        # alpha = min(0.99, ...) per layer; a pixel stops before T would drop below 1e-4
        centre = ref["alpha"][0, 9, 12, 0]
        assert 1 - centre >= 1e-4 - 1e-12 and centre > 0.999
    if name == "far_outside_frustum":
        assert radii[0] == 0 and radii[1] == 0 and radii[2] > 0
    if name == "tiny_opacity":
        assert radii[0] == 0 and radii[1] == 0 and radii[2] > 0
    if name == "sub_pixel":
        assert (radii > 0).all()  # the 0.3 px^2 dilation keeps them visible


@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_empty_scene(backend):
    if backend == "cpu" and not cpu_kernel_available():
        pytest.skip("cpu kernel not built")
    vm, K = look_at_camera(10, 7)
    z = torch.zeros(0, 3, requires_grad=True)
    bg = torch.tensor([0.1, 0.2, 0.3])
    render, alpha, meta = rasterization(z, torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0),
                                        torch.zeros(0, 3), vm, K, 10, 7, backgrounds=bg,
                                        render_mode="RGB+D", backend=backend)
    assert render.shape == (1, 7, 10, 4) and alpha.shape == (1, 7, 10, 1)
    assert torch.equal(render[..., :3], bg.expand(1, 7, 10, 3)) and (alpha == 0).all()
    assert meta["means2d"].shape == (1, 0, 2) and meta["radii"].shape == (1, 0)
    render.sum().backward()
    assert z.grad.shape == (0, 3)


@pytest.mark.parametrize("size", [(1, 1), (37, 23), (17, 41), (16, 16), (33, 8)])
def test_odd_image_sizes(size):
    W, H = size
    scene = random_scene(60, W, H, seed=W * 100 + H, dtype=torch.float64, sigma_px=1.5)
    ref = run(scene, "torch", render_mode="RGB+D")
    assert ref["render"].shape == (1, H, W, 4)
    if cpu_kernel_available():
        for ts in (8, 16):
            assert_close(run(scene, "cpu", render_mode="RGB+D", tile_size=ts), ref, rtol=1e-10, atol=1e-10)


# ------------------------------------------------------------------------------------------------
# meta: means2d gradient, contribution


@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_means2d_grad_and_contribution_mask(backend):
    if backend == "cpu" and not cpu_kernel_available():
        pytest.skip("cpu kernel not built")
    scene = random_scene(100, 32, 24, seed=4, dtype=torch.float64, sigma_px=2.0)
    mask = torch.zeros(1, 24, 32, dtype=torch.bool)
    mask[:, 5:15, 10:20] = True
    args = _leaf(scene)
    render, alpha, meta = rasterization(**args, backend=backend, contribution_mask=mask)
    meta["means2d"].retain_grad()
    render.sum().backward()
    g2 = meta["means2d"].grad
    assert g2 is not None and g2.shape == (1, 100, 2)
    assert (g2[meta["radii"] == 0] == 0).all() and g2.abs().sum() > 0
    # contrib with a mask = contrib of the masked pixels only: compare with an all-true mask
    _, _, meta_all = rasterization(**scene, backend=backend)
    assert (meta["contrib"] <= meta_all["contrib"] + 1e-12).all()
    assert meta["contrib"].sum() < meta_all["contrib"].sum()
    # sum over Gaussians of contrib = sum over (masked) pixels of alpha
    torch.testing.assert_close(meta_all["contrib"].sum(), alpha.sum().detach())
    torch.testing.assert_close(meta["contrib"].sum(), alpha.detach()[0, ..., 0][mask[0]].sum())
    # Gaussians whose footprint misses the mask contribute nothing
    m2 = meta["means2d"].detach()[0]
    far = (m2[:, 0] < 10 - 8 * 3.4) | (m2[:, 0] > 20 + 8 * 3.4)
    assert (meta["contrib"][0][far] == 0).all()


# ------------------------------------------------------------------------------------------------
# input validation


def _valid_args():
    scene = random_scene(10, 16, 12, seed=0)
    scene.pop("sh_degree")
    return scene


@pytest.mark.parametrize("name", ["means", "quats", "scales", "opacities", "colors", "viewmats", "Ks",
                                  "backgrounds"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_inputs_raise(name, bad):
    args = _valid_args()
    args["backgrounds"] = torch.zeros(3)
    x = args[name].clone()
    x.view(-1)[min(3, x.numel() - 1)] = bad
    args[name] = x
    with pytest.raises(NonFiniteInputError, match=name) as info:
        rasterization(**args)
    assert isinstance(info.value, ValueError) and isinstance(info.value, NonFiniteError)
    assert info.value.fix and "holds 1 NaN/inf value(s)" in str(info.value)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_count_non_finite_counts_nan_and_inf(dtype, monkeypatch):
    x = torch.randn(7, 5, 3, dtype=dtype) * 1e30  # large but finite values are not flagged
    assert count_non_finite(x) == 0
    x[1, 2, 0], x[3, 0, 1], x[6, 4, 2] = float("nan"), float("inf"), -float("inf")
    assert count_non_finite(x) == 3
    assert count_non_finite(x.transpose(0, 2)) == 3  # non-contiguous views too
    assert count_non_finite(x[:, :, :1]) == 1
    assert count_non_finite(x.requires_grad_()) == 3  # a leaf needing gradients
    assert count_non_finite(torch.zeros(0, 3, dtype=dtype)) == 0
    assert count_non_finite(torch.arange(5)) == 0  # integers cannot hold NaN
    big = torch.zeros(1 << 21, dtype=dtype)  # from 2^18 values the kernel scans with threads
    nan, inf = float("nan"), float("inf")
    big[[0, 12345, (1 << 20) + 7, (1 << 21) - 1]] = torch.tensor([nan, inf, -inf, nan], dtype=dtype)
    assert count_non_finite(big) == 4 and count_non_finite(big[1:-1]) == 2
    for n in ((1 << 18) - 1, 1 << 18, (1 << 18) + 3, 1001):  # either side of the threads' threshold,
        part = big[(1 << 21) - n:].clone()  # and lengths no vector width divides
        part[[0, n // 2]] = torch.tensor([inf, -inf], dtype=dtype)
        assert count_non_finite(part) == 3, n
    # the torch fallback (no kernel, or a tensor off the CPU) gives the same counts
    monkeypatch.setattr(_raster_cpu, "count_nonfinite", lambda t: None)
    assert count_non_finite(x) == 3 and count_non_finite(x[:, :, 2:]) == 1
    assert count_non_finite(torch.randn(4, dtype=dtype) * 1e30) == 0


def test_first_non_finite_names_the_first_bad_tensor():
    good, bad = torch.ones(4, 3), torch.ones(4, 3)
    bad[2, 1] = float("nan")
    assert first_non_finite({"a": good, "b": None, "c": good.double()}) is None
    assert first_non_finite({"a": good, "b": bad, "c": bad.clone()}) == "b"
    assert first_non_finite({"a": None, "x": bad * float("inf")}) == "x"
    assert first_non_finite({}) is None


@pytest.mark.parametrize("change, match", [
    ({"means": torch.zeros(10, 2)}, "means"),
    ({"quats": torch.zeros(9, 4)}, "quats"),
    ({"scales": torch.zeros(10, 3, dtype=torch.float64)}, "scales"),
    ({"opacities": torch.zeros(10, 1)}, "opacities"),
    ({"colors": torch.zeros(10, 3, 3)}, "colors"),
    ({"viewmats": torch.eye(3)[None]}, "viewmats"),
    ({"Ks": torch.eye(3)[None].expand(2, 3, 3)}, "Ks"),
    ({"width": 0}, "width"),
    ({"height": 2.5}, "height"),
    ({"render_mode": "RGBD"}, "render_mode"),
    ({"tile_size": 32}, "tile_size"),
    ({"backend": "cuda"}, "backend"),
    ({"near_plane": 0.0}, "near_plane"),
    ({"sh_degree": 4}, "sh_degree"),
    ({"backgrounds": torch.zeros(4)}, "backgrounds"),
    ({"contribution_mask": torch.zeros(1, 12, 16)}, "contribution_mask"),
    ({"means": torch.zeros(10, 3, dtype=torch.float16)}, "means"),
])
def test_invalid_inputs_raise(change, match):
    args = _valid_args()
    args.update(change)
    with pytest.raises(RasterizerInputError, match=match) as info:
        rasterization(**args)
    assert isinstance(info.value, ValueError)


def _sh_pair_against_one_tensor(dtype: torch.dtype, sh_degree: int, backend: str, device: str = "cpu") -> tuple:
    """Renders two cameras with ``colors`` as the one [N,16,3] tensor and as the pair (sh0, shN);
    returns (one, pair, sh, nb): each a tuple (render, alpha, d means, d colours as [N,16,3])."""
    scene = random_scene(200, 40, 30, seed=5, dtype=dtype, sigma_px=2.0, sh_degree=3)
    vm2 = torch.eye(4, dtype=dtype)
    vm2[:3, 3] = torch.tensor([0.3, -0.1, 0.4], dtype=dtype)
    scene["viewmats"] = torch.cat([scene["viewmats"], vm2[None]])
    scene["Ks"] = scene["Ks"].expand(2, -1, -1).contiguous()
    scene = {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    sh = scene.pop("colors")
    scene.pop("sh_degree")

    def render_and_grads(colors_of):
        means = scene["means"].detach().clone().requires_grad_(True)
        leaves = [sh.detach().clone().requires_grad_(True)] if colors_of == "one" else \
            [sh[:, :1].detach().clone().requires_grad_(True), sh[:, 1:].detach().clone().requires_grad_(True)]
        colors = leaves[0] if colors_of == "one" else tuple(leaves)
        render, alpha, _ = rasterization(**{**scene, "means": means}, colors=colors, sh_degree=sh_degree,
                                         backend=backend)
        w = torch.randn(render.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
        ((render * w.to(render)).sum() + alpha.sum()).backward()
        g_sh = leaves[0].grad if colors_of == "one" else torch.cat([leaves[0].grad, leaves[1].grad], 1)
        return render.detach(), alpha.detach(), means.grad, g_sh

    return render_and_grads("one"), render_and_grads("pair"), sh, (sh_degree + 1) ** 2


@requires_kernel
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("sh_degree", [0, 2, 3])
def test_sh_as_dc_and_rest_pair_matches_one_tensor(dtype, sh_degree):
    """``colors=(sh0, shN)`` (a model's two parameters, read in place by the cpu kernel) renders and
    differentiates bitwise like the one [N,16,3] tensor, two cameras, on the cpu and torch backends;
    the coefficients above the degree get zero gradients."""
    for backend in ("cpu", "torch"):
        one, pair, sh, nb = _sh_pair_against_one_tensor(dtype, sh_degree, backend)
        for a, b in zip(one, pair):
            assert torch.equal(a, b), backend
        assert one[3].shape == sh.shape and (one[3][:, nb:] == 0).all() and one[3][:, :nb].abs().sum() > 0
        assert one[0].abs().sum() > 0


@pytest.mark.parametrize("backend", ["cpu", "torch"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("sh_degree, mode", [(None, "RGB+ED"), (3, "RGB")])
def test_grad_mask_zeroes_the_others_gradients_and_keeps_the_rest(backend, dtype, sh_degree, mode):
    """``grad_mask``: the Gaussians outside it get exactly zero gradients (every parameter, and on
    the cpu backend means2d); those inside get bitwise the gradients they get without a mask; the
    render is the same."""
    if backend == "cpu" and not cpu_kernel_available():
        pytest.skip("needs the cpu kernel")
    scene = random_scene(200, 40, 30, seed=7, dtype=dtype, sigma_px=2.0, sh_degree=sh_degree)
    mask = torch.rand(200, generator=torch.Generator().manual_seed(2)) < 0.3
    kw = {"render_mode": mode, "backgrounds": torch.tensor([0.2, 0.5, 0.9], dtype=dtype)}
    full = run(scene, backend, **dict(kw))
    part = run(scene, backend, **dict(kw), grad_mask=mask)
    for k in ("render", "alpha", "contrib", "radii"):
        assert torch.equal(full[k], part[k]), k
    for k in (["g_means2d"] if backend == "cpu" else []) + ["g_" + n for n in PARAMS]:
        dim = 1 if k == "g_means2d" else 0
        inside = full[k].index_select(dim, mask.nonzero()[:, 0])
        assert torch.equal(part[k].index_select(dim, mask.nonzero()[:, 0]), inside), k
        assert (part[k].index_select(dim, (~mask).nonzero()[:, 0]) == 0).all(), k
        assert inside.abs().sum() > 0 and full[k].index_select(dim, (~mask).nonzero()[:, 0]).abs().sum() > 0, k
    with pytest.raises(RasterizerInputError, match="grad_mask"):
        rasterization(**{k: v for k, v in scene.items()}, backend=backend, grad_mask=mask[:-1])
    with pytest.raises(RasterizerInputError, match="grad_mask"):
        rasterization(**{k: v for k, v in scene.items()}, backend=backend, grad_mask=mask.float())


def test_sh_pair_is_checked():
    args = _valid_args()
    sh0, shN = torch.zeros(10, 1, 3), torch.zeros(10, 3, 3)
    rasterization(**{**args, "colors": (sh0, shN)}, sh_degree=1)
    with pytest.raises(RasterizerInputError, match="SH"):
        rasterization(**{**args, "colors": (sh0, shN)}, sh_degree=2)
    with pytest.raises(RasterizerInputError, match=r"colors\[0\] \(sh0\)"):
        rasterization(**{**args, "colors": (torch.zeros(10, 2, 3), shN)}, sh_degree=1)
    with pytest.raises(RasterizerInputError, match="must be a torch.Tensor"):
        rasterization(**{**args, "colors": (sh0, shN)})  # a pair only holds SH coefficients
    bad = shN.clone()
    bad[3, 1, 2] = float("nan")
    with pytest.raises(NonFiniteInputError, match=r"colors\[1\] \(shN\) holds 1 NaN"):
        rasterization(**{**args, "colors": (sh0, bad)}, sh_degree=1)


@requires_kernel
def test_check_finite_false_skips_the_scan_and_culls_non_finite_gaussians():
    """``check_finite=False`` (for a caller that checked its inputs) does not scan them; a Gaussian
    with a NaN centre or an infinite scale then renders as if absent (the projection culls it)."""
    scene = random_scene(60, 24, 18, seed=2)
    scene.pop("sh_degree")
    bad = {k: (v.clone() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    bad["means"][0, 1] = float("nan")
    bad["scales"][1] = float("inf")
    with pytest.raises(NonFiniteInputError):
        rasterization(**bad, backend="cpu")
    render, alpha, _ = rasterization(**bad, backend="cpu", check_finite=False)
    keep = {k: (v[2:] if k in PARAMS else v) for k, v in scene.items()}
    render_ref, alpha_ref, _ = rasterization(**keep, backend="cpu")
    assert torch.equal(render, render_ref) and torch.equal(alpha, alpha_ref)


def test_sh_needs_enough_coefficients():
    args = _valid_args()
    args["colors"] = torch.zeros(10, 4, 3)
    with pytest.raises(RasterizerInputError, match="SH"):
        rasterization(**args, sh_degree=2)
    rasterization(**args, sh_degree=1)  # 4 coefficients are enough for degree 1


def test_depth_modes_need_no_colors():
    args = _valid_args()
    args["colors"] = None
    render, alpha, _ = rasterization(**args, render_mode="ED")
    assert render.shape == (1, 12, 16, 1)
    with pytest.raises(RasterizerInputError, match="colors"):
        rasterization(**args, render_mode="RGB")


# ------------------------------------------------------------------------------------------------
# backends


def test_auto_backend_and_missing_kernel_fallback(monkeypatch):
    args = _valid_args()
    _, _, meta = rasterization(**args)
    assert meta["backend"] == ("cpu" if cpu_kernel_available() else "torch")
    from sgpor_pipeline.gaussians import rasterizer

    monkeypatch.setattr(_raster_cpu, "_lib", None)
    monkeypatch.setattr(_raster_cpu, "_loaded", True)
    monkeypatch.setattr(_raster_cpu, "_load_error", "simulated")
    monkeypatch.setattr(rasterizer, "_warned", set())
    with pytest.warns(RuntimeWarning, match="simulated"):
        _, _, meta = rasterization(**args, backend="cpu")
    assert meta["backend"] == "torch"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rasterization(**args)  # warned once only


def test_constants_match_kernel_source():
    from pathlib import Path

    src = (Path(rcommon.__file__).resolve().parents[1] / "csrc" / "raster.h").read_text()
    assert "kAlphaMax = 0.99;" in src and rcommon.ALPHA_MAX == 0.99
    assert "kTMin = 1e-4;" in src and rcommon.T_MIN == 1e-4
    assert "kMaxSigma = 0.5 * 3.33 * 3.33;" in src and rcommon.MAX_EXTEND == 3.33
    assert "kFrustumMargin = 0.3;" in src and rcommon.FRUSTUM_MARGIN == 0.3
    assert "kAlphaMin = 1.0 / 255.0;" in src and rcommon.ALPHA_MIN == 1.0 / 255.0


requires_gsplat = pytest.mark.skipif(not torch.cuda.is_available(), reason="gsplat parity needs a CUDA device")


def _cuda(scene: dict) -> dict:
    return {k: (v.cuda() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}


@requires_gsplat
def test_gsplat_parity():
    pytest.importorskip("gsplat")
    scene = random_scene(500, 64, 48, seed=1, sigma_px=2.0, sh_degree=2)
    ref = run(scene, "torch", render_mode="RGB+ED")
    gs = run(_cuda(scene), "gsplat", render_mode="RGB+ED")
    assert gs["backend"] == "gsplat"
    # gsplat clamps alpha at 0.999 (we use 0.99) and bounds footprints slightly differently
    diff = (gs["render"].cpu()[..., :3] - ref["render"][..., :3]).abs()
    assert diff.mean() < 0.02
    # where both keep a Gaussian: gsplat writes no means2d for one it culls (seen on an H200: 2 of 1000
    # values differ, at Gaussians one backend culls)
    both = (gs["radii"].cpu() > 0) & (ref["radii"] > 0)
    torch.testing.assert_close(gs["means2d"].cpu()[both], ref["means2d"][both], rtol=1e-4, atol=1e-3)
    assert ((gs["radii"].cpu() > 0) == (ref["radii"] > 0)).float().mean() > 0.95


@requires_gsplat
@pytest.mark.parametrize("mode", ["RGB", "D", "ED", "RGB+ED"])
def test_gsplat_matches_torch_below_the_alpha_clamp(mode):
    """With opacities <= 0.9 neither backend's alpha clamp (0.99 here, 0.999 in gsplat) binds and
    the opacity-aware footprint is the alpha >= 1/255 test of both: images, alphas and every
    gradient agree to float32 rounding, on CUDA tensors for both backends."""
    pytest.importorskip("gsplat")
    scene = _cuda(random_scene(400, 64, 48, seed=7, sigma_px=2.0, sh_degree=1 if "RGB" in mode else None,
                               opacity_range=(0.05, 0.9)))
    kw = {"render_mode": mode}
    if mode.startswith("RGB"):
        kw["backgrounds"] = torch.tensor([0.2, 0.5, 0.9], device="cuda")
    ref = run(scene, "torch", **dict(kw))
    gs = run(scene, "gsplat", **dict(kw))
    assert gs["backend"] == "gsplat" and ref["backend"] == "torch"
    assert_close({k: gs[k] for k in ("render", "alpha", "depths", "means2d", "conics")}, ref,
                 rtol=1e-4, atol=1e-4)
    for k in ("g_means", "g_quats", "g_scales", "g_opacities", "g_colors", "g_backgrounds"):
        if ref.get(k) is None:
            continue
        x, y = gs[k].double(), ref[k].double()
        rel = float((x - y).norm() / y.norm().clamp_min(1e-12))
        assert rel < 1e-3, f"{k}: relative error {rel:.2e}"


@requires_gsplat
def test_gsplat_contribution_matches_torch():
    """meta["contrib"] (the object score's input) from gsplat's extra rasterization equals the
    reference's sum of alpha*T, over all pixels and over a contribution mask."""
    pytest.importorskip("gsplat")
    scene = _cuda(random_scene(400, 64, 48, seed=5, sigma_px=2.0, opacity_range=(0.05, 0.9)))
    mask = torch.zeros(1, 48, 64, dtype=torch.bool, device="cuda")
    mask[:, 10:30, 20:50] = True
    for cm in (None, mask):
        _, _, ref = rasterization(**scene, backend="torch", contribution_mask=cm)
        _, _, gs = rasterization(**scene, backend="gsplat", contribution_mask=cm)
        assert gs["contrib"].shape == ref["contrib"].shape == (1, 400)
        torch.testing.assert_close(gs["contrib"], ref["contrib"], rtol=1e-4, atol=1e-4)
    assert float(ref["contrib"].sum()) > 10.0  # the mask covers a real share of the image


@requires_gsplat
@pytest.mark.parametrize("sh_degree", [0, 3])
def test_gsplat_takes_the_sh_pair(sh_degree):
    """The trainer passes (sh0, shN) on CUDA too: gsplat (which concatenates them) renders the pair as
    the one tensor, and the gradients reach both parameters (to float32 rounding: gsplat's backward
    adds with atomics, in no fixed order)."""
    pytest.importorskip("gsplat")
    one, pair, sh, nb = _sh_pair_against_one_tensor(torch.float32, sh_degree, "gsplat", "cuda")
    torch.testing.assert_close(pair[0], one[0], rtol=0, atol=1e-6)
    torch.testing.assert_close(pair[1], one[1], rtol=0, atol=1e-6)
    for a, b in zip(one[2:], pair[2:]):
        torch.testing.assert_close(b, a, rtol=1e-4, atol=1e-6)
    assert pair[3].shape == sh.shape and (pair[3][:, nb:] == 0).all() and pair[3][:, :nb].abs().sum() > 0
