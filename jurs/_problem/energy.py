"""Energies, metrics, the PIA step size and the hand-derived gradients.

Everything is written with the two linear maps of ``jurs._model.spline``: ``F`` (coefficient
grid -> values at the samples) and its transpose ``T``. With ``W = F(w)``:

* ``g = F(w C) / W`` (eq. 14) and the collocation transpose ``D^T v = w * T(v / W)``;
* ``nabla_C E_d = 2 D^T r`` and ``nabla_w E_d = 2 (C * T(r / W) - T(r g / W))``
  (docs/design.md section 2).

D (3m x NM) is never formed, nor any (samples x 16) array of its rows. Arrays indexed by
sample are in the problem's slot order (see [`jurs.Problem`][]).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array

from .._model.basis import num_cells, patches_to_grid
from .._model.local import LocalBasis
from .._model.precision import scalar_array
from .._model.spline import (
    ImplicitSpline,
    bspline_transpose,
    bspline_values,
    rational_terms,
    rational_values,
    transpose_and_sum,
    values_apart,
)
from .problem import Problem


def rational_residuals(problem: Problem, control: Array, weights: Array):
    """``(r, W, g)`` at the slots: ``r = g(x_k) - b_k`` (0 at padding), ``W = W(x_k)`` and
    ``g(x_k)`` (eq. 14, 18)."""
    denom, g = rational_values(problem.local, control, weights)
    return problem.mask * (g - problem.targets), denom, g


def layout_residuals(
    local: LocalBasis,
    mask: Array,
    targets: Array,
    control: Array,
    weights: Array,
    inv_denom: Array | None = None,
):
    """``(r, mask / W, g)`` in the kernels' layout
    ([`LocalBasis.to_layout`][jurs.internal.LocalBasis.to_layout], in which ``mask`` and
    ``targets`` are given): W and F(w C) in one pass apart, then eq. 14 and 18; F(w C) alone
    where ``inv_denom`` (``mask / W`` for these weights) is known. What a solver step and
    the metrics use; 0 at padding."""
    if inv_denom is None:
        both = values_apart(local, jnp.stack([weights, weights * control]))
        inv_denom, numerator = mask / both[0], both[1]
    else:
        numerator = values_apart(local, weights * control)
    g = numerator * inv_denom  # eq. 14
    return mask * (g - targets), inv_denom, g


def bspline_residuals(problem: Problem, control: Array) -> Array:
    """``r = f(x_k) - b_k`` at the slots for the polynomial B-spline f of eq. 2 (w = 1, so
    W = 1 by the partition of unity and one evaluation suffices); 0 at padding."""
    return problem.mask * (bspline_values(problem.local, control) - problem.targets)


def collocation_transpose(problem: Problem, weights: Array, denom: Array, values: Array) -> Array:
    """``D^T v`` for the collocation D of eq. 23 (rows ``w_ij B_ij / W``): ``w * T(v / W)``.

    ``values`` may carry leading axes (several vectors in one pass); masked slots count 0.
    """
    return weights * bspline_transpose(problem.local, problem.mask * values / denom, problem.shape)


def data_energy(problem: Problem, control: Array, weights: Array) -> Array:
    """E_d(C, w) = sum_k (g(x_k) - b_k)^2 over all 3m samples (eq. 16; eq. 6 when w = 1)."""
    r = rational_residuals(problem, control, weights)[0]
    return jnp.sum(r * r)


def regulariser(control: Array) -> Array:
    """R(C) = sum_ij ||RC_ij||^2 (eq. 31): the four neighbour differences of every
    coefficient (six in 3D: the same sum over the 6-neighbour grid), missing neighbours
    counting 0. Each grid edge appears twice."""
    diffs = [jnp.diff(control, axis=a) for a in range(control.ndim)]
    total = jnp.sum(diffs[0] * diffs[0])
    for d in diffs[1:]:
        total = total + jnp.sum(d * d)
    return 2.0 * total


def objective(problem: Problem, control: Array, weights: Array, lam) -> Array:
    """E(C, w) + lambda R(C) (eq. 32), lambda being the objective's weight (see
    docs/design.md section 3). One compiled program a problem size (lambda enters it as
    an array): ``jax.grad`` of it outside a jit compiles its passes whole, not op by op."""
    return _compiled_objective(problem, control, weights, scalar_array(lam, problem.samples.dtype))


@eqx.filter_jit
def _compiled_objective(problem: Problem, control: Array, weights: Array, lam) -> Array:
    return data_energy(problem, control, weights) + lam * regulariser(control)


def grid_laplacian(control: Array) -> Array:
    """(L C)_ij = deg_ij C_ij - sum of 4-neighbours (6-neighbours in 3D), free boundary
    (edge-replicated pad makes a missing neighbour contribute 0)."""
    p = jnp.pad(control, 1, mode="edge")
    inner = tuple(slice(1, -1) for _ in range(control.ndim))
    out = 2.0 * control.ndim * p[inner]
    for axis in range(control.ndim):
        for window in (slice(2, None), slice(None, -2)):
            out = out - p[inner[:axis] + (window,) + inner[axis + 1 :]]
    return out


def regulariser_grad(control: Array) -> Array:
    """nabla_C R(C) = 4 L C (eq. 34), hand-derived."""
    return 4.0 * grid_laplacian(control)


def data_energy_grad_control(problem: Problem, control: Array, weights: Array) -> Array:
    """nabla_C E_d = 2 D^T r, hand-derived (docs/design.md section 2)."""
    r, denom, _ = rational_residuals(problem, control, weights)
    return 2.0 * collocation_transpose(problem, weights, denom, r)


def weight_gradient(problem: Problem, control: Array, r: Array, denom: Array, g: Array) -> Array:
    """nabla_w E_d (eq. 19) from the residuals: ``2 sum_k r_k B_ij(x_k) (C_ij - g_k) / W_k``
    = ``2 (C * T(r / W) - T(r g / W))``, hand-derived (docs/design.md section 2)."""
    t = bspline_transpose(problem.local, jnp.stack([r / denom, r * g / denom]), problem.shape)
    return 2.0 * (control * t[0] - t[1])


def data_energy_grad_weights(problem: Problem, control: Array, weights: Array) -> Array:
    """nabla_w E_d = 2 sum_k r_k B_i B_j(x_k) (C_ij - g(x_k)) / W(x_k) (eq. 19), hand-derived."""
    r, denom, g = rational_residuals(problem, control, weights)
    return weight_gradient(problem, control, r, denom, g)


def collocation_column_sums(problem: Problem, weights: Array) -> Array:
    """Column sums of D (eq. 23) as an (N, M) grid. D >= 0 with unit row sums, so
    ||D^T D||_inf equals the largest of these (docs/design.md section 2). Masked slots are
    not rows."""
    denom = rational_values(problem.local, jnp.zeros_like(weights), weights)[0]
    return collocation_transpose(problem, weights, denom, jnp.ones_like(denom))


def step_size(problem: Problem, weights: Array) -> Array:
    """mu = 2 / ||D^T D||_inf (eq. 13 and 25), without forming D^T D."""
    return step_size_from_column_sums(collocation_column_sums(problem, weights))


def step_size_from_column_sums(column_sums: Array) -> Array:
    """mu = 2 / ||D^T D||_inf (eq. 13 and 25) from D's column sums, whose largest is that
    norm (see [`collocation_column_sums`][jurs.internal.collocation_column_sums]); for
    callers that have them from a shared pass over the samples."""
    return 2.0 / jnp.max(column_sums)


def residuals(problem: Problem, control: Array, weights: Array):
    """Residuals with the explicit collocation rows of eq. 23, for row-based algorithms
    and checks: ``(r, wb, denom, g)`` with row ``k`` of D equal to ``wb[k] / denom[k]``
    (see ``jurs._model.spline.rational_terms``). ``r`` is 0 at padding slots."""
    wb, denom, g = rational_terms(problem.local, control, weights)
    return problem.mask * (g - problem.targets), wb, denom, g


def transpose_apply(problem: Problem, rows: Array) -> Array:
    """Sum explicit per-slot 16-term rows onto the grid: ``sum_k rows[k, ..., j]`` at the
    coefficient of term j; with ``rows = D_k v_k`` this is ``D^T v``.

    ``rows`` is ``(S, 16)`` -> ``(N, M)``, or ``(S, c, 16)`` -> ``(c, N, M)``. The solvers use
    the cheaper [`collocation_transpose`][jurs.internal.collocation_transpose]; this is for
    row-based algorithms.
    """
    per_cell = jax.ops.segment_sum(rows, problem.local.cell, num_segments=num_cells(problem.shape))
    return patches_to_grid(jnp.moveaxis(per_cell, 0, -2), problem.shape)


def metric_sums(problem: Problem, spline: ImplicitSpline) -> dict[str, Array]:
    """The sums over the samples that [`metrics`][jurs.internal.metrics] reads:
    ``residual_sums`` of the spline's residuals and ``column_sums`` (D's column sums for
    eq. 25, a grid). Each is a sum over the samples (``E_max`` a maximum), so the metrics
    of samples taken in parts follow from the parts' sums added (``metrics_from_sums``).
    Padding counts 0."""
    local = problem.local
    # In the kernels' layout (padding 0), as the solvers' steps work: no per-slot reorder.
    mask, targets = local.to_layout(problem.mask), local.to_layout(problem.targets)
    weights = spline.weights
    r, inv_denom, _ = layout_residuals(local, mask, targets, spline.control, weights)
    # eq. 25 from the W above: D's column sums w * T(1 / W).
    col_sums, _ = transpose_and_sum(local, inv_denom[None], problem.shape, layout=True)
    return dict(residual_sums(problem, r), column_sums=weights * col_sums[0])


def residual_sums(problem: Problem, r: Array) -> dict[str, Array]:
    """``E_d`` (eq. 16), ``on_data2`` (the sum of ``g(P_i)^2``), ``count`` (the data
    points) and ``E_max`` (eq. 37) of the residuals ``r`` in the kernels' layout (0 at
    padding)."""
    is_data = problem.local.to_layout(problem.is_data)
    on_data = is_data * r  # targets there are 0, so r = g(P_i)
    # The three totals in one reduction (each is a few kernels of its own otherwise).
    e_d, on_data2, count = jnp.sum(jnp.stack([r * r, on_data * on_data, is_data]), axis=-1)
    return {"E_d": e_d, "on_data2": on_data2, "count": count, "E_max": jnp.max(jnp.abs(on_data))}


def metrics_from_sums(sums: dict, reg, lam=0.0) -> dict:
    """The metrics of eq. 35-37 from the sums over the samples (``metric_sums``'s: of all
    the samples, or their parts' sums added) and the regulariser's value ``reg``: ``E``,
    ``E_d``, ``R``, ``E_ave``, ``E_max``, and ``mu`` (eq. 25) where the sums hold D's
    ``column_sums``. The one place these are built, for either basis: plain arithmetic,
    so host floats stay host floats (nothing compiled) and arrays stay arrays."""
    out = {
        "E": sums["E_d"] + lam * reg,
        "E_d": sums["E_d"],
        "R": reg,
        "E_ave": sums["on_data2"] / sums["count"],
        "E_max": sums["E_max"],
    }
    if "column_sums" in sums:
        out["mu"] = step_size_from_column_sums(sums["column_sums"])
    return out


def metrics(problem: Problem, spline: ImplicitSpline, lam=0.0) -> dict[str, Array]:
    """Evaluation metrics of eq. 35-37 for a fitted spline.

    ``E = E_d + lam R(C)`` (eq. 35) with the ``lam`` given; ``E_ave = mean g(P_i)^2`` and
    ``E_max = max |g(P_i)|`` over the m data points only (eq. 36-37); ``E_d`` and ``R`` are
    also returned, and ``mu`` of eq. 25 for the spline's weights. Padding (``mask`` 0) is
    left out of every sum.
    """
    return metrics_from_sums(metric_sums(problem, spline), regulariser(spline.control), lam)


def eta(value_without, value_with):
    """eta = |E - E'| / E x 100 % (paper, Section V): the improvement of E' over E."""
    return jnp.abs((value_without - value_with) / value_without) * 100.0
