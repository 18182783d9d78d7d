"""``fit_adaptive(..., method="multigrid")``: the hierarchy's normal equations solved on the
host by conjugate gradients preconditioned by a V-cycle over the hierarchy's own nested
spaces (``jurs._linalg.thb_multigrid``; docs/multigrid.md, "The multilevel solve of the
hierarchy")."""

from __future__ import annotations

import numpy as np

from .._linalg.thb_multigrid import multigrid_cg
from .._problem.adaptive import AdaptiveProblem


def normal_system(problem: AdaptiveProblem, matrices, lam: float, row_weights=None):
    """``(D^T S D + lam 2 G^T W G, D^T S b)`` on the host (SciPy CSR, float64) from the
    matrices ``(D, 2 G^T W G)`` of ``assemble_adaptive_problem``; ``S`` the samples'
    ``row_weights`` (None: 1)."""
    from scipy import sparse

    collocation, regulariser = (matrix.tocsr() for matrix in matrices)
    weighted = collocation
    if row_weights is not None:
        weighted = sparse.csr_matrix(sparse.diags(np.asarray(row_weights, float)) @ collocation)
    transposed = weighted.T.tocsr()
    matrix = sparse.csr_matrix(collocation.T.tocsr() @ weighted + lam * regulariser)
    return matrix, transposed @ np.asarray(problem.targets, float)


def solve_host_multigrid(
    problem: AdaptiveProblem,
    matrices,
    lam: float,
    rtol: float,
    max_steps: int,
    row_weights=None,
    start=None,
    **options,
) -> tuple[np.ndarray, int, float]:
    """``(control, steps, relative residual)`` as ``solve_host_cg`` returns them (the stop
    rule ``|r| <= rtol |D^T S b|``; ``row_weights`` and ``start`` as its), by CG
    preconditioned by one multilevel V-cycle a step
    (``jurs._linalg.thb_multigrid.ThbMultigrid``; ``options`` go to it). Not
    differentiable."""
    matrix, rhs = normal_system(problem, matrices, lam, row_weights)
    return multigrid_cg(problem.hierarchy, matrix, rhs, rtol, max_steps, start=start, **options)
