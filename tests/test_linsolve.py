"""Sparse SPD solves over holes: the multigrid path for large systems agrees with the direct one."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from sgpor_pipeline.removal import holes, linsolve, sbm


def laplacian_2d(h: int, w: int) -> sp.csr_matrix:
    """The 5-point Laplacian of an h x w grid with Dirichlet boundary (SPD)."""
    def line(k: int) -> sp.csr_matrix:
        return sp.diags([-np.ones(k - 1), 2 * np.ones(k), -np.ones(k - 1)], [-1, 0, 1])
    return sp.csr_matrix(sp.kron(sp.identity(h), line(w)) + sp.kron(line(h), sp.identity(w)))


def test_multigrid_solves_one_and_several_right_hand_sides():
    A = laplacian_2d(60, 70)
    x = np.random.default_rng(0).random((A.shape[0], 3))
    b = A @ x
    assert linsolve.solve_spd_multigrid(A, b).shape == (A.shape[0], 3)
    assert np.abs(linsolve.solve_spd_multigrid(A, b) - x).max() < 1e-7
    assert np.abs(linsolve.solve_spd_multigrid(A, b[:, 1]) - x[:, 1]).max() < 1e-7
    assert linsolve.solve_spd_multigrid(sp.csr_matrix((0, 0)), np.zeros(0)).shape == (0,)
    assert linsolve.large(linsolve.DIRECT_MAX_UNKNOWNS + 1) and not linsolve.large(linsolve.DIRECT_MAX_UNKNOWNS)


def test_multigrid_is_bit_reproducible_and_leaves_the_global_generator_alone(monkeypatch):
    """pyamg draws random start vectors for its spectral-radius estimates from numpy's global generator:
    the solve seeds it (and restores it), so two solves of one system agree bit for bit whatever the
    generator's state, and a caller's random stream continues as if nothing had drawn from it."""
    import contextlib

    A = laplacian_2d(70, 80)
    b = A @ np.random.default_rng(2).random(A.shape[0])
    np.random.seed(11)
    first = linsolve.solve_spd_multigrid(A, b)
    np.random.seed(12)
    expected = np.random.rand(3)
    np.random.seed(12)
    second = linsolve.solve_spd_multigrid(A, b)
    assert np.array_equal(first, second)
    assert np.array_equal(np.random.rand(3), expected)  # (the solve drew nothing from the caller's stream)
    monkeypatch.setattr(linsolve, "_seeded_global_random", contextlib.nullcontext)
    np.random.seed(11)
    a = linsolve.solve_spd_multigrid(A, b)
    np.random.seed(12)
    assert not np.array_equal(a, linsolve.solve_spd_multigrid(A, b))  # (what the seeding prevents)


def _blend_inputs():
    rng = np.random.default_rng(1)
    h, w = 180, 240
    yy, xx = np.mgrid[:h, :w]
    # a disc and a region on the image border (Neumann there)
    region = ((yy - 90) ** 2 + (xx - 120) ** 2 < 60 ** 2) | ((yy < 25) & (xx < 40))
    return rng.random((h, w, 3)), rng.random((h, w, 3)), region


def test_poisson_blend_by_multigrid_matches_the_direct_solve(monkeypatch):
    image, guide, region = _blend_inputs()
    direct = sbm.poisson_blend(image, guide, region)
    monkeypatch.setattr(linsolve, "DIRECT_MAX_UNKNOWNS", 0)
    iterative = sbm.poisson_blend(image, guide, region)
    assert np.abs(direct - iterative).max() < 1e-7
    assert np.array_equal(iterative[~region], image[~region])  # only the region is solved


def test_depth_completion_by_multigrid_matches_the_direct_solve(monkeypatch):
    h, w = 200, 260
    yy, xx = np.mgrid[:h, :w]
    depth = (2.0 + 0.01 * xx + 0.02 * yy + 0.05 * np.sin(xx / 13.0)).astype(np.float32)
    valid = np.ones((h, w), bool)
    valid[150:190, 200:250] = False  # an invalid pocket away from the hole
    valid[:20] = False  # and a band along the border, touching the hole
    hole = (yy - 90) ** 2 + (xx - 120) ** 2 < 70 ** 2
    direct = holes.complete_depth(depth, valid, hole)
    monkeypatch.setattr(linsolve, "DIRECT_MAX_UNKNOWNS", 0)
    iterative = holes.complete_depth(depth, valid, hole)
    assert np.all(np.isfinite(iterative)) and iterative.dtype == np.float32
    assert np.abs(direct - iterative).max() < 1e-5 * float(depth.max())
