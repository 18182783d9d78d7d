"""Energies, metrics, the PIA step size and the hand-derived gradients.

All functions take the coefficient grids C and w explicitly and touch each sample's 16
local terms only: D (3m x NM) is never formed. ``D^T v`` is one segment sum of 16-wide rows
per cell followed by a fold of the cell patches onto the grid (:func:`transpose_apply`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array

from ._basis import grid_to_patches, num_cells, patches_to_grid
from ._problem import Problem
from ._spline import ImplicitSpline, rational_terms


def transpose_apply(problem: Problem, rows: Array) -> Array:
    """Sum per-sample 16-term rows onto the grid: ``sum_k rows[k, ..., j]`` at the
    coefficient of term j. With ``rows = D_k * v_k`` this is ``D^T v``.

    ``rows`` is ``(n, 16)`` -> ``(N, M)``, or ``(n, c, 16)`` -> ``(c, N, M)`` for several
    products in one pass over the samples (one segment sum, one read of the cell indices).
    """
    per_cell = jax.ops.segment_sum(rows, problem.local.cell, num_segments=num_cells(problem.shape))
    if rows.ndim == 2:
        return patches_to_grid(per_cell, problem.shape)
    return jax.vmap(lambda p: patches_to_grid(p, problem.shape), in_axes=1)(per_cell)


def residuals(problem: Problem, control: Array, weights: Array):
    """``r = g(x_k) - b_k`` at the 3m samples (0 at masked-out padding), with the rational
    terms it was built from.

    Returns ``(r, wb, denom, g)``, see :func:`jurs._spline.rational_terms`.
    """
    wb, denom, g = rational_terms(problem.local, control, weights)
    return problem.mask * (g - problem.targets), wb, denom, g


def data_energy(problem: Problem, control: Array, weights: Array) -> Array:
    """E_d(C, w) = sum_k (g(x_k) - b_k)^2 over all 3m samples (eq. 16; eq. 6 when w = 1)."""
    r = residuals(problem, control, weights)[0]
    return jnp.sum(r * r)


def regulariser(control: Array) -> Array:
    """R(C) = sum_ij ||RC_ij||^2 (eq. 31): the four neighbour differences of every
    coefficient, missing neighbours counting 0. Each grid edge appears twice."""
    dx = jnp.diff(control, axis=0)
    dy = jnp.diff(control, axis=1)
    return 2.0 * (jnp.sum(dx * dx) + jnp.sum(dy * dy))


def objective(problem: Problem, control: Array, weights: Array, lam) -> Array:
    """E(C, w) + lambda R(C) (eq. 32), lambda being the objective's weight (see DESIGN 3)."""
    return data_energy(problem, control, weights) + lam * regulariser(control)


def grid_laplacian(control: Array) -> Array:
    """(L C)_ij = deg_ij C_ij - sum of 4-neighbours, free boundary (edge-replicated pad
    makes a missing neighbour contribute 0)."""
    p = jnp.pad(control, 1, mode="edge")
    c = p[1:-1, 1:-1]
    return 4.0 * c - p[2:, 1:-1] - p[:-2, 1:-1] - p[1:-1, 2:] - p[1:-1, :-2]


def regulariser_grad(control: Array) -> Array:
    """nabla_C R(C) = 4 L C (eq. 34), hand-derived."""
    return 4.0 * grid_laplacian(control)


def data_energy_grad_control(problem: Problem, control: Array, weights: Array) -> Array:
    """nabla_C E_d = 2 D^T r, hand-derived (DESIGN 2)."""
    r, wb, denom, _ = residuals(problem, control, weights)
    return 2.0 * transpose_apply(problem, wb * (r / denom)[:, None])


def weight_grad_rows(problem: Problem, control: Array, r: Array, wb: Array, denom: Array,
                     g: Array) -> Array:
    """Per-sample terms of nabla_w E_d (eq. 19): ``2 r_k B_ij(x_k) (C_ij - g_k) / W_k``.

    ``B_ij = wb / w_ij``; written as ``wb (C_ij - g) / (w_ij W)`` it would divide by w, so
    the plain basis products are used instead.
    """
    c_rows = grid_to_patches(control)[problem.local.cell]
    return problem.local.products * (2.0 * r / denom)[:, None] * (c_rows - g[:, None])


def data_energy_grad_weights(problem: Problem, control: Array, weights: Array) -> Array:
    """nabla_w E_d = 2 sum_k r_k B_i B_j(x_k) (C_ij - g(x_k)) / W(x_k) (eq. 19), hand-derived."""
    r, wb, denom, g = residuals(problem, control, weights)
    return transpose_apply(problem, weight_grad_rows(problem, control, r, wb, denom, g))


def collocation_column_sums(problem: Problem, weights: Array) -> Array:
    """Column sums of D (eq. 23) as an (N, M) grid. D >= 0 with unit row sums, so
    ||D^T D||_inf equals the largest of these (DESIGN 2). Masked samples are not rows."""
    _, wb, denom, _ = residuals(problem, jnp.zeros_like(weights), weights)
    return transpose_apply(problem, wb * (problem.mask / denom)[:, None])


def step_size(problem: Problem, weights: Array) -> Array:
    """mu = 2 / ||D^T D||_inf (eq. 13 and 25), without forming D^T D."""
    return 2.0 / jnp.max(collocation_column_sums(problem, weights))


def metrics(problem: Problem, spline: ImplicitSpline, lam=0.0) -> dict[str, Array]:
    """Evaluation metrics of eq. 35-37 for a fitted spline.

    ``E = E_d + lam R(C)`` (eq. 35) with the ``lam`` given; ``E_ave = mean g(P_i)^2`` and
    ``E_max = max |g(P_i)|`` over the m data points only (eq. 36-37); ``E_d`` and ``R`` are
    also returned, and ``mu`` of eq. 25 for the spline's weights. Padding (``mask`` 0) is
    left out of every sum.
    """
    r = residuals(problem, spline.control, spline.weights)[0]
    m = problem.num_points
    on_data = r[:m]  # targets there are 0, so r = g(P_i) (0 at padding)
    e_d = jnp.sum(r * r)
    reg = regulariser(spline.control)
    return {
        "E": e_d + lam * reg,
        "E_d": e_d,
        "R": reg,
        "E_ave": jnp.sum(on_data * on_data) / jnp.sum(problem.mask[:m]),
        "E_max": jnp.max(jnp.abs(on_data)),
        "mu": step_size(problem, spline.weights),
    }


def eta(value_without, value_with):
    """eta = |E - E'| / E x 100 % (paper, Section V): the improvement of E' over E."""
    return jnp.abs((value_without - value_with) / value_without) * 100.0
