"""The paper's Algorithm 1 (IURS) as a user of the paper would write it in NumPy: the baseline.

A straightforward port, with no tricks: the dense tensor-product B-spline matrix ``B``
(3m x NM) is built once with ``scipy.interpolate.BSpline.design_matrix``, and every step
rebuilds the dense collocation matrix ``D`` of eq. 23 from the current weights:

1. ``w <- max(w - tau nabla_w E, min_weight)``                          (eq. 20, projected)
2. ``W = B w``, ``D = B * w / W[:, None]``                               (eq. 14, 23)
3. ``mu = 2 / ||D^T D||_inf`` = 2 / max column sum of D                 (eq. 25)
4. ``C <- C + mu D^T (b - D C) - lam nabla_C R(C)``                     (eq. 33, 34)
5. ``E = ||D C - b||^2 + lam R(C)`` and ``nabla_w E`` at the new (C, w)  (eq. 35, 19)

This is the same order of operations as [`jurs.IURS`][] (the weight gradient used by a
step is the one computed at the end of the previous step, or by ``init``), so the
iterates agree with jurs to rounding; ``benchmarks/tests/test_numpy_port.py`` checks it. Memory is
O(m N M): it only runs where the dense matrices fit (see ``dense_bytes``).
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import BSpline

#: Margin of the automatic box, as a fraction of the samples' longest side (jurs's default).
DEFAULT_MARGIN = 0.1


def offset_samples(points, normals, offset: float, eps: float):
    """Eq. 4-5 and 9: samples ``[P, P + d n, P - d n]`` with targets ``[0, +eps, -eps]``."""
    points = np.asarray(points, float)
    normals = np.asarray(normals, float)
    normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    samples = np.concatenate([points, points + offset * normals, points - offset * normals])
    m = len(points)
    targets = np.concatenate([np.zeros(m), np.full(m, eps), np.full(m, -eps)])
    return samples, targets


def auto_box(samples, margin: float = DEFAULT_MARGIN):
    """Bounding box of the samples grown by ``margin`` x its longest side (as jurs does)."""
    lo, hi = samples.min(axis=0), samples.max(axis=0)
    pad = margin * np.max(hi - lo)
    return lo - pad, hi + pad


def dense_basis(samples, lower, upper, shape) -> np.ndarray:
    """Dense ``(S, N*M)`` matrix of the tensor-product cubic B-splines at the samples.

    Uniform knots with ``N - 3`` cells across the box, extended three cells past each end,
    so every point of the box lies under 4 x 4 non-zero functions that sum to one.
    Column ``i * M + j`` is ``B_i(x) B_j(y)``.
    """
    axes = []
    for axis in range(2):
        n = shape[axis]
        h = (upper[axis] - lower[axis]) / (n - 3)
        knots = lower[axis] + (np.arange(n + 4) - 3.0) * h
        axes.append(BSpline.design_matrix(samples[:, axis], knots, 3).toarray())
    bx, by = axes
    return (bx[:, :, None] * by[:, None, :]).reshape(len(samples), -1)


def dense_bytes(num_points: int, shape) -> int:
    """Bytes of one dense 3m x NM float64 matrix (B, D and temporaries are each this big)."""
    return 3 * num_points * shape[0] * shape[1] * 8


def laplacian(c: np.ndarray) -> np.ndarray:
    """Graph Laplacian of the 4-neighbour grid, free boundary: ``deg * C - sum of neighbours``."""
    p = np.pad(c, 1, mode="edge")  # a replicated edge contributes C - C = 0
    return 4.0 * c - p[2:, 1:-1] - p[:-2, 1:-1] - p[1:-1, 2:] - p[1:-1, :-2]


def regulariser(c: np.ndarray) -> float:
    """R(C) of eq. 31: every grid edge's squared difference, counted twice."""
    return 2.0 * (np.sum(np.diff(c, axis=0) ** 2) + np.sum(np.diff(c, axis=1) ** 2))


class Problem:
    """Dense basis ``B``, targets ``b`` and grid shape of one fit."""

    def __init__(self, points, normals, *, grid, offset=0.1, eps=0.01, domain=None):
        self.shape = (grid, grid) if np.isscalar(grid) else tuple(grid)
        samples, self.b = offset_samples(points, normals, offset, eps)
        if domain is None:
            self.lower, self.upper = auto_box(samples)
        else:
            self.lower, self.upper = (np.asarray(d, float) for d in domain)
        self.B = dense_basis(samples, self.lower, self.upper, self.shape)


def collocation(problem: Problem, w: np.ndarray):
    """``(W, D)``: W = B w at the samples and the dense collocation D = B * w / W (eq. 23)."""
    W = problem.B @ w
    return W, problem.B * w / W[:, None]


def energy_and_weight_grad(problem: Problem, c, w, lam: float, W=None, D=None):
    """``(E, nabla_w E_d)`` at (C, w): eq. 35 and the weight gradient of eq. 19,
    ``dE/dw_ij = 2 sum_k r_k B_ij(x_k) (C_ij - g_k) / W_k``. ``c`` and ``w`` are flat;
    ``W, D`` of these weights are rebuilt unless given."""
    B, b = problem.B, problem.b
    if D is None:
        W, D = collocation(problem, w)
    g = D @ c
    r = g - b
    energy = r @ r + lam * regulariser(c.reshape(problem.shape))
    grad_w = 2.0 * ((B.T @ (r / W)) * c - B.T @ (r * g / W))
    return energy, grad_w


def init(problem: Problem, lam: float = 0.0, control=None, weights=None):
    """Algorithm 1, lines 3-6: C = 0, w = 1 (or the ``(N, M)`` arrays given), and the
    initial energy (and weight gradient)."""
    nm = problem.shape[0] * problem.shape[1]
    c = np.zeros(nm) if control is None else np.asarray(control, float).ravel().copy()
    w = np.ones(nm) if weights is None else np.asarray(weights, float).ravel().copy()
    energy, grad_w = energy_and_weight_grad(problem, c, w, lam)
    return {"C": c, "w": w, "grad_w": grad_w, "E": energy, "mu": 0.0}


def step(problem: Problem, state: dict, *, tau: float, lam: float, min_weight: float = 1e-6):
    """One iteration of Algorithm 1 (lines 8-12), dense: see the module docstring."""
    c = state["C"]
    w = np.maximum(state["w"] - tau * state["grad_w"], min_weight)  # eq. 20, kept positive
    W, D = collocation(problem, w)  # eq. 23 with the new weights, built once per step
    mu = 2.0 / D.sum(axis=0).max()  # eq. 25: D >= 0 with unit row sums
    grad_r = 4.0 * laplacian(c.reshape(problem.shape)).ravel()  # eq. 34
    c = c + mu * (D.T @ (problem.b - D @ c)) - lam * grad_r  # eq. 33
    # Line 12: the energy at the new (C, w), with the same D; its weight gradient feeds
    # the next step's eq. 20.
    energy, grad_w = energy_and_weight_grad(problem, c, w, lam, W, D)
    return {"C": c, "w": w, "grad_w": grad_w, "E": energy, "mu": mu}
