"""Sparse symmetric positive definite solves of the Laplace / Poisson systems over holes.

The Poisson blend of a fill (:func:`~sgpor_pipeline.removal.sbm.poisson_blend`) and the harmonic
completion of a hole's depth (:func:`~sgpor_pipeline.removal.holes.complete_depth`) solve one
5-point Laplacian per hole. A direct solver's fill-in grows faster than the unknowns, and it was
the memory peak of both the remove and the inpaint stage: lund + box at 960x718 (28 views), 1.04 GB
in ``spsolve`` and 1.25 GB in ``splu`` of 2.3 / 2.4 GB (memray, session 31). Large systems are
therefore solved by conjugate gradients preconditioned with smoothed-aggregation algebraic
multigrid (pyamg), whose memory is linear in the unknowns. A disc of 1.13 M unknowns, three
right-hand sides: SuperLU 29.7 s and +2.5 GB, AMG-CG 11.9 s and +0.2 GB; 126 k unknowns: 1.0 s /
+193 MB against 1.2 s / +25 MB. Small systems (all of them at the benchmarks' 256-384 px) keep
the direct solver, so their results are exactly what they were.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numpy as np
import scipy.sparse as sp

# At most this many unknowns are solved directly (SuperLU): about 150 MB of fill-in for a disc.
DIRECT_MAX_UNKNOWNS = 100_000
# Relative residual at which the iterative solve stops: far below the 8-bit colour and the depth
# precision that use the solution.
ITERATIVE_TOL = 1e-10
MAX_ITERATIONS = 500  # (AMG-CG takes 10-30 on these systems)


def large(n: int) -> bool:
    """Whether a system of ``n`` unknowns is solved iteratively (:func:`solve_spd_multigrid`)."""
    return n > DIRECT_MAX_UNKNOWNS


@contextlib.contextmanager
def _seeded_global_random(seed: int = 0) -> Iterator[None]:
    """numpy's global generator seeded, and restored afterwards. pyamg starts its spectral-radius
    estimates (the Jacobi weight of its prolongation smoother) from ``np.random.rand``; unseeded, two
    solves of one system differed in the last bits (1 float32 ulp of the completed depth at a few pixels
    of 3 of 96 views: the remove stage was not bit-reproducible). pyamg's documentation asks for exactly
    this seeding; restoring the state leaves every other user of the global generator as it was."""
    state = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(state)


def solve_spd_multigrid(A: sp.spmatrix, b: np.ndarray) -> np.ndarray:
    """Solve ``A x = b`` for a sparse symmetric positive definite ``A`` [n, n] (a Laplacian with
    boundary terms) by AMG-preconditioned CG. ``b`` is [n] or [n, k] (k right-hand sides sharing
    the multigrid hierarchy); the result has its shape, float64."""
    import pyamg

    b = np.asarray(b, np.float64)
    if A.shape[0] == 0:
        return np.zeros_like(b)
    cols = b.reshape(len(b), -1)
    with _seeded_global_random():  # (bit-reproducible: see _seeded_global_random)
        hierarchy = pyamg.smoothed_aggregation_solver(sp.csr_matrix(A), symmetry="symmetric")
        x = np.stack([hierarchy.solve(cols[:, j], tol=ITERATIVE_TOL, accel="cg", maxiter=MAX_ITERATIONS)
                      for j in range(cols.shape[1])], axis=1)
    return x.reshape(b.shape)
