"""Per-point values (colour, intensity, labels, any ``(m, k)`` array) carried onto a fitted
zero set: ``jurs.fit_attributes`` and the ``AttributeField`` it returns.

**One more right-hand side.** An attribute is fitted on the basis of g (the same grid and
box, the cubic B-spline) by the same regularised least squares as g itself: the samples of
g's problem (every point P and its offsets ``P +/- d n``, eq. 4), each given its point's
value, and the normal equations ``(D^T D + 2 lam L) A = D^T v`` of g's system
(docs/design.md section 3) with one right-hand side a value column. The matrix is g's own,
assembled once; on curves it is factorised once (dense or block Cholesky, as
[`jurs.LeastSquares`][] chooses) and every column solved against that factor; on surfaces
every column runs the same Jacobi-preconditioned CG as g's final solve. The offsets carry
each value a distance d along the normal, so the field is constant across the thin band
around the surface where meshes put their vertices.

**No bleeding across sheets.** Two sheets of a zero set nearer than a cell (the two faces
of a thin wall, a fold) share the basis functions between them, so a single smooth field
would average their colours. The two faces of a closed surface face opposite ways, and
that is what separates them here: every sample is weighted by how much its normal faces
each of the ``2 d`` axis directions ``+-e_a``, ``beta_a(n) = max(0, +-n_a)^2`` (these
sum to 1 over the directions for a unit n), and a numerator ``N_a`` (the values times
``beta_a``) and a denominator ``D_a`` (``beta_a`` alone) are fitted for each direction, all
against the one matrix. At a point x with g's unit normal ``nu = grad g / |grad g|``,

    a(x) = (sum_a beta_a(nu) N_a(x) + tau N(x)) / (sum_a beta_a(nu) D_a(x) + tau D(x))

with ``N`` and ``D`` the unweighted fits and ``tau = SIDE_FLOOR``. A sample whose normal
opposes nu has ``beta_a(n) beta_a(nu) = 0`` in every direction, so it reaches x only
through ``tau`` (a part in ``1 / SIDE_FLOOR``); samples facing the same way weigh at least
``1 / d``. The ratio is that of eq. 14: a weighted mean of the samples' values, without
a division by a fitted density that could vanish (``D`` is 1 wherever data are).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Float

from .._linalg.normal import NormalEquations, normal_equations
from .._model.adaptive import AdaptiveSpline
from .._model.function import AbstractSpline
from .._model.spline import ImplicitSpline, bspline_transpose, bspline_values, local_basis
from .._problem.problem import build_problem
from .._problem.validate import check_nonnegative, numeric_array
from .._solution.solution import Solution
from ..solvers._cascade import COARSEST_COEFFICIENTS, coarse_system, transferred_start
from ..solvers._least_squares import (
    LeastSquares,
    solve_normal_equations,
    surface_linear_solver,
)

#: ``tau`` of the module notes: the share of the unweighted fit in an attribute's value,
#: which keeps the ratio defined where no sample faces the way g's normal does, and is all
#: that a sheet facing the other way contributes.
SIDE_FLOOR = 1e-3
#: Dimensionless smoothing (``jurs.auto_settings``'s scale-free lambda) of an attribute
#: fitted to a bare spline, which records no lambda of its own.
ATTRIBUTE_SMOOTHING = 1e-6
#: Largest number of cells a side of the uniform grid an attribute of an
#: [`jurs.AdaptiveSpline`][] is fitted on (its finest level otherwise).
ADAPTIVE_MAX_CELLS = {2: 256, 3: 48}


def side_weights(normals: Array) -> Array:
    """``beta_a(n) = max(0, +-n_a)^2`` of unit ``normals (n, d)``: ``(n, 2 d)``, the
    directions ``+e_0, -e_0, +e_1, ...``; each row sums to 1."""
    signed = jnp.stack([normals, -normals], axis=-1).reshape(normals.shape[0], -1)
    return jnp.maximum(signed, 0.0) ** 2


class AttributeField(eqx.Module):
    """Values fitted on the basis of a zero set's spline, read from the side each point
    faces ([`jurs.fit_attributes`][] builds it; the rule is in ``jurs._fit.attributes``).

    Calling it on ``(n, d)`` points returns ``(n, k)`` values (``(k,)`` for one point), in
    the units the values were given (colours in [0, 1] or 0-255 come back the same way;
    a weighted mean, so one-hot labels come back as shares that sum to 1). Meant for
    points on or near the zero set, such as a mesh's vertices: the side is read from g's
    gradient there.

    Attributes:
        geometry: the spline g whose zero set the values describe.
        coefficients: ``(2 d + 1, k + 1) + grid``: for the unweighted fit and each of the
            ``2 d`` directions, the k value columns and the weight column.
        lower, upper: the box of the coefficient grid (g's box).
    """

    geometry: AbstractSpline
    coefficients: Array
    lower: Array
    upper: Array

    @property
    def ndim(self) -> int:
        return self.lower.shape[0]

    @property
    def num_values(self) -> int:
        """k, the values a point carries."""
        return self.coefficients.shape[1] - 1

    def __call__(self, x: Float[ArrayLike, "*n d"]) -> Float[Array, "*n k"]:
        x = jnp.asarray(x, self.coefficients.dtype)
        single = x.ndim == 1
        x = jnp.atleast_2d(x)
        if x.shape[-1] != self.ndim:
            raise ValueError(
                f"points must have shape (n, {self.ndim}) for a {self.ndim}D field, got {x.shape}"
            )
        out = _evaluate(self, x)
        return out[0] if single else out


@eqx.filter_jit
def _evaluate(field: AttributeField, x: Array) -> Array:
    """``field`` at ``x (n, d)``: the module notes' ratio; ``(n, k)``."""
    grid = field.coefficients.shape[2:]
    c = field.coefficients.shape[:2]
    local = local_basis(x, field.lower, field.upper, grid)
    values = bspline_values(local, field.coefficients.reshape((-1,) + grid))
    values = values.reshape(c + (x.shape[0],))  # (2d + 1, k + 1, n)
    gradient = field.geometry.grad(x)
    length = jnp.linalg.norm(gradient, axis=1, keepdims=True)
    nu = gradient / jnp.where(length > 0, length, 1.0)
    beta = jnp.concatenate(
        [jnp.full((x.shape[0], 1), SIDE_FLOOR, x.dtype), side_weights(nu)], axis=1
    )  # (n, 2d + 1)
    mixed = jnp.einsum("nc,ckn->nk", beta, values)
    return mixed[:, :-1] / mixed[:, -1:]


@eqx.filter_jit
def _gradient(spline, x: Array) -> Array:
    return spline.grad(x)


def _spline_and_settings(fit):
    """``(spline, lam, offset)`` from a Solution (its lambda and offset, None where it
    records none) or a spline."""
    if isinstance(fit, Solution):
        lam = fit.metrics.get("lam")
        offset = None if fit.settings is None else fit.settings.offset
        return fit.spline, (None if lam is None else float(lam)), offset
    if isinstance(fit, AbstractSpline):
        return fit, None, None
    raise TypeError(
        f"fit must be a jurs.Solution, ImplicitSpline or AdaptiveSpline, got {type(fit).__name__}"
    )


def _checked_values(points, values, normals, ndim: int):
    """``(points (m, d), values (m, k), normals or None)`` as float64 NumPy arrays, or a
    ValueError naming the argument."""
    p = numeric_array("points", points).astype(float)
    if p.ndim != 2 or p.shape[1] != ndim:
        raise ValueError(f"points must have shape (m, {ndim}) for a {ndim}D spline, got {p.shape}")
    v = numeric_array("values", values).astype(float)
    if v.ndim not in (1, 2) or v.shape[0] != p.shape[0]:
        raise ValueError(
            f"values must have shape (m,) or (m, k) with one row a point (m = {p.shape[0]}), "
            f"got {v.shape}"
        )
    v = v.reshape(p.shape[0], -1)
    if v.shape[1] == 0:
        raise ValueError("values must hold at least one column, got shape (m, 0)")
    n = None
    if normals is not None:
        n = numeric_array("normals", normals).astype(float)
        if n.shape != p.shape:
            raise ValueError(f"normals must have the same shape as points {p.shape}, got {n.shape}")
    for name, a in (("points", p), ("values", v), ("normals", n)):
        if a is not None and not np.isfinite(a).all():
            bad = ~np.isfinite(a).all(axis=1)
            raise ValueError(f"{name} contain NaN or Inf (first at row {int(np.argmax(bad))})")
    if p.shape[0] < 1:
        raise ValueError("points: need at least one point")
    if n is not None and (np.abs(n).max(axis=1) == 0).any():
        row = int(np.argmax(np.abs(n).max(axis=1) == 0))
        raise ValueError(f"normals must be non-zero (zero-length normal at row {row})")
    return p, v, n


def _attribute_grid(spline, grid) -> tuple[int, ...]:
    """The attributes' grid: ``grid`` where given, else the spline's own
    (``_own_grid``)."""
    if grid is not None:
        from .._problem.validate import normalise_grid

        return normalise_grid(grid, spline.ndim)
    return _own_grid(spline)


@functools.singledispatch
def _own_grid(spline: AbstractSpline) -> tuple[int, ...]:
    """The default attribute grid of ``spline``, by its basis."""
    raise TypeError(f"no attribute grid for a {type(spline).__name__}")


@_own_grid.register
def _(spline: ImplicitSpline) -> tuple[int, ...]:
    return tuple(spline.shape)  # its own coefficient grid


@_own_grid.register
def _(spline: AdaptiveSpline) -> tuple[int, ...]:
    # The finest level's uniform grid, capped: the attributes need no hierarchy.
    cap = ADAPTIVE_MAX_CELLS[spline.ndim]
    return tuple(min(int(c), cap) + 3 for c in spline.finest_cells)


def fit_attributes(
    fit: Solution | ImplicitSpline | AdaptiveSpline,
    points: Float[ArrayLike, "m d"],
    values: Float[ArrayLike, "m k"] | Float[ArrayLike, " m"],
    *,
    normals: Float[ArrayLike, "m d"] | None = None,
    offset: float | None = None,
    lam: float | None = None,
    grid=None,
) -> AttributeField:
    """Fit per-point ``values`` as fields on the basis of a fitted zero set, read from the
    side each point faces.

    The values (colour ``(m, 3)`` in [0, 1] or 0-255, intensity ``(m,)``, one-hot labels,
    any ``(m, k)``) are fitted by g's own regularised least squares, one right-hand side
    a column, split by the direction the samples face so that two sheets of the zero set
    nearer than a cell keep their own values (``jurs._fit.attributes`` has the rule).
    Evaluate the result at a mesh's vertices: ``field(vertices)``.

    Args:
        fit: the [`jurs.Solution`][] of the fit (its lambda and offset are used), or its
            spline ([`jurs.ImplicitSpline`][], or [`jurs.AdaptiveSpline`][], whose
            attributes live on a uniform grid over its box, the finest level's cells up
            to ``ADAPTIVE_MAX_CELLS`` a side).
        points: ``(m, d)`` points the values belong to, usually the fitted cloud; inside
            the spline's box.
        values: ``(m,)`` or ``(m, k)`` finite numbers, one row a point.
        normals: ``(m, d)`` outward normals of the points (normalised here), or None to
            take g's gradient there.
        offset: the distance d of the offset samples that carry each value along its
            normal; None takes the fit's (``sol.settings.offset``), or a quarter of a
            cell for a spline alone.
        lam: the lambda of the regulariser (``E_d + lam R``); None takes the fit's
            (``sol.metrics["lam"]``), or the scale-free lambda of
            ``ATTRIBUTE_SMOOTHING`` for a spline alone.
        grid: the attribute basis's grid; None takes g's own (see ``fit`` for an
            adaptive spline).

    Returns:
        An [`AttributeField`][jurs.AttributeField]: ``field(x)`` gives ``(n, k)`` values.

    Raises:
        ValueError: points not ``(m, d)`` of the spline's dimension, values not one row a
            point, normals not shaped like the points, NaN or Inf anywhere, zero normals,
            points outside the spline's box, a negative lam or a non-positive offset.
        TypeError: ``fit`` is not a Solution or spline; arrays that are not numbers.
    """
    spline, fit_lam, fit_offset = _spline_and_settings(fit)
    ndim = spline.ndim
    p, v, n = _checked_values(points, values, normals, ndim)
    lower = np.asarray(spline.lower, float)
    upper = np.asarray(spline.upper, float)
    outside = ((p < lower) | (p > upper)).any(axis=1)
    if outside.any():
        raise ValueError(
            f"points outside the spline's box (first at row {int(np.argmax(outside))}): "
            "attributes are fitted on the spline's own grid"
        )
    shape = _attribute_grid(spline, grid)
    h = float(np.max((upper - lower) / (np.asarray(shape) - 3.0)))  # cell_width, on the host
    d = offset if offset is not None else fit_offset if fit_offset is not None else h / 4
    check_nonnegative("offset", d, strict=True)
    weight = lam if lam is not None else fit_lam
    weight = weight if weight is not None else _default_lam(p, lower, upper, h)
    check_nonnegative("lam", weight)
    offset, lam = float(d), float(weight)
    dtype = jnp.result_type(float)
    if n is None:
        n = np.array(_gradient(spline, jnp.asarray(p, dtype)), float)
        flat = ~(np.linalg.norm(n, axis=1) > 0)
        n[flat] = np.eye(ndim)[0]  # g flat there: any side, the unweighted fit decides
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    problem = build_problem(
        p, n, shape, offset, offset, (lower, upper), 0.0, bucket_size=1, dtype=dtype
    )
    coefficients = _solve_columns(problem, jnp.asarray(v, dtype), lam)
    return AttributeField(
        spline, coefficients, jnp.asarray(lower, dtype), jnp.asarray(upper, dtype)
    )


def _default_lam(points: np.ndarray, lower, upper, cell: float) -> float:
    from .settings import scale_free_lam

    diagonal = float(np.linalg.norm(np.ptp(points, axis=0))) or float(np.linalg.norm(upper - lower))
    return scale_free_lam(ATTRIBUTE_SMOOTHING, 3 * len(points), diagonal, lower, upper, cell)


def _slot_values(problem, per_point: Array) -> Array:
    """Per-point columns ``(m, c)`` as per-slot values ``(c, S)`` of ``problem``: every
    sample takes its point's values (the paper's order is ``[P, P + d n, P - d n]``), 0 at
    padding."""
    point = problem.sample_index % problem.num_points
    return per_point[point].T * problem.mask


def _column_solve(operator, rhs: Array, start: Array) -> Array:
    """Every column of ``rhs (c,) + grid`` solved against the one ``operator`` by g's
    final surface CG (``surface_linear_solver``), from ``start``."""

    def solve(column, begin):
        return solve_normal_equations(operator, column, begin, surface_linear_solver(column))[0]

    return jax.vmap(solve)(rhs, start)


def _surface_columns(problem, per_point: Array, lam) -> Array:
    """g's final solve on surfaces for every column: CG from the cascadic start
    (``jurs.solvers._cascade``), the coarse grid's matrix assembled and factorised once
    for all the columns (a column whose coarse solve broke down starts from 0, as g's
    start keeps its own: ``transferred_start``)."""
    operator = normal_equations(problem).regularised(lam)
    rhs = bspline_transpose(problem.local, _slot_values(problem, per_point), problem.shape)
    coarse = coarse_system(problem, lam)
    if coarse is None:  # a grid as small as the cascade's coarse one: solved exactly
        return _cholesky_columns(operator, rhs)
    level, _, system = coarse
    start = _cholesky_columns(
        system, bspline_transpose(level.local, _slot_values(level, per_point), level.shape)
    )
    zeros = jnp.zeros(problem.shape, start.dtype)
    start = jax.vmap(lambda s: transferred_start(s, problem.shape, zeros))(start)
    return _column_solve(operator, rhs, start)


def _cholesky_columns(operator, rhs: Array) -> Array:
    """Every column of ``rhs`` solved against ``operator`` by one dense Cholesky
    factorisation (lineax factorises an operator that the columns do not batch once)."""
    solve = lambda column: solve_normal_equations(  # noqa: E731
        operator, column, jnp.zeros_like(column), lx.Cholesky()
    )[0]
    return jax.vmap(solve)(rhs)


@eqx.filter_jit
def _solve_columns(problem, values: Array, lam) -> Array:
    """The ``(2 d + 1, k + 1) + grid`` coefficients of ``AttributeField``: every value
    column and the weight column, unweighted and weighted by each direction, solved
    against g's regularised normal equations on ``problem``."""
    m = problem.num_points
    beta = jnp.concatenate(
        [jnp.ones((m, 1), values.dtype), side_weights(problem.normals)], axis=1
    )  # (m, 2d + 1)
    columns = jnp.concatenate([values, jnp.ones((m, 1), values.dtype)], axis=1)  # (m, k + 1)
    per_point = (beta[:, :, None] * columns[:, None, :]).reshape(m, -1)
    c = beta.shape[1:] + columns.shape[1:]
    if problem.ndim == 3:
        return _surface_columns(problem, per_point, lam).reshape(c + tuple(problem.shape))
    normal = normal_equations(problem)
    rhs = bspline_transpose(problem.local, _slot_values(problem, per_point), problem.shape)
    if np.prod(problem.shape) <= COARSEST_COEFFICIENTS:
        # Small grids: one dense factorisation, without the fallbacks of g's solve (each
        # compiled once more under the columns' vmap), which lam > 0 makes unneeded.
        return _cholesky_columns(normal.regularised(lam), rhs).reshape(c + tuple(problem.shape))
    solver = LeastSquares(lam=lam)

    def solve(column):  # g's own exact solve; the factorisation is shared by the columns
        system = NormalEquations(normal.stencil, column, jnp.zeros((), column.dtype))
        return solver.solve_assembled(problem, system, lam, jnp.zeros_like(column))[0]

    return jax.vmap(solve)(rhs).reshape(c + tuple(problem.shape))
