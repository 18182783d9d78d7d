"""The fitting problem as a residual vector or a scalar loss over C or (C, log w).

Shared by the optimistix and jaxopt wrappers. ``E_d + lam R`` is a sum of squares:
the 3m data residuals ``g(x_k) - b_k`` (eq. 16) and, since ``R = 2 sum_edges (C_a - C_b)^2``
(eq. 31), one residual ``sqrt(2 lam) (C_a - C_b)`` per grid edge.

Joint fits optimise ``(C, v)`` with ``w = exp(v)``: weights stay positive without
projection. g is unchanged when every weight is scaled by the same factor, so the loss has
a flat direction in v; one extra residual, ``mean(v)``, removes it. It costs nothing at the
optimum (rescaling w to ``mean(log w) = 0`` changes neither g nor E), and it keeps
Gauss-Newton systems non-singular.
"""

from __future__ import annotations

from typing import cast

import jax.numpy as jnp
from jax import Array

from .._linalg.normal import normal_equations
from .._model.spline import ImplicitSpline
from .._problem.energy import residuals
from .._problem.problem import Problem
from ._least_squares import DEFAULT_RIDGE, solve_by_default


def unpack(y, joint: bool) -> tuple[Array, Array]:
    """Parameters -> ``(C, w)``: ``y`` is C, or ``(C, v)`` with ``w = exp(v)``."""
    if joint:
        control, log_weights = y
        return control, jnp.exp(log_weights)
    return y, jnp.ones_like(y)


def residual_vector(y, problem: Problem, lam, joint: bool):
    """Residuals whose squares sum to ``E_d + lam R`` (+ ``mean(v)^2`` for joint fits);
    a tuple of arrays."""
    control, weights = unpack(y, joint)
    r = residuals(problem, control, weights)[0]
    scale = jnp.sqrt(2.0 * lam)
    out = (r, scale * jnp.diff(control, axis=0), scale * jnp.diff(control, axis=1))
    if joint:
        out = out + (jnp.mean(y[1])[None],)
    return out


def scalar_loss(y, problem: Problem, lam, joint: bool) -> Array:
    """``E_d + lam R`` (eq. 32) (+ ``mean(v)^2`` for joint fits): sum of squared residuals."""
    return cast(Array, sum(jnp.sum(r * r) for r in residual_vector(y, problem, lam, joint)))


def initial_parameters(
    problem: Problem, spline: ImplicitSpline, lam, joint: bool, warm_start: bool
):
    """Start of the search. B-spline: the start spline's C. Joint: ``v = log w`` shifted to
    mean 0, and, with ``warm_start``, C replaced by the exact minimiser for those fixed
    weights (one normal-equation solve): the joint search then starts at the best C for
    the start weights (the B-spline optimum for the default w = 1), with
    ``LeastSquares``' default ridge, which keeps the solve finite where ``lam = 0``
    leaves the system numerically singular (Example 1, 120 points, 15 x 15)."""
    if not joint:
        return spline.control
    log_weights = jnp.log(spline.weights)
    log_weights = log_weights - jnp.mean(log_weights)
    control = spline.control
    if warm_start:
        normal = normal_equations(problem, spline.weights)
        control, _ = solve_by_default(normal.regularised(lam), normal.rhs, control, DEFAULT_RIDGE)
    return control, log_weights


def to_spline(problem: Problem, y, joint: bool) -> ImplicitSpline:
    control, weights = unpack(y, joint)
    return ImplicitSpline(control, weights, problem.lower, problem.upper)
