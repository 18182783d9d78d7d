"""A fitting problem on a THB hierarchy (``jurs._model.hierarchy``): the samples of eq. 4-5,
their leaves, and the energy ``E_d + lam R`` (eq. 16, 31) over the active functions.

The data term reads ``g(x_k) = sum_j B_j(t_k) a[p_kj]`` (``a`` the cascaded coefficients,
``p_kj`` the ``4^d`` functions over sample k's leaf): one gather per sample, whose
transpose is one scatter. Which leaf holds a sample is structure, found on the host once;
the local coordinates ``t_k`` are computed from the samples in JAX, so a loss through a fit
differentiates with respect to the points.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Float

from .._model.hierarchy import (
    Hierarchy,
    build_hierarchy,
    cascade,
    cascade_matrix,
    hierarchy_regulariser,
    refine_near,
)
from .._model.leaves import hierarchy_basis, leaf_terms, locate_leaves
from .._model.precision import on_device
from .._threads import product_by_rows
from .energy import metrics_from_sums
from .problem import offset_samples


class AdaptiveProblem(eqx.Module):
    """Samples, targets and their leaves on a THB hierarchy.

    ``samples (S, d)`` and ``targets (S,)`` are eq. 4-5's (``[P, P + d n, P - d n]``);
    ``positions (S, 4^d)`` index the cascaded coefficients over each sample's leaf and
    ``cell (S, d)``, ``level (S,)`` name the leaf; ``data_diagonal`` and
    ``regulariser_diagonal`` ``(n,)`` are the diagonals of ``D^T D`` and of ``2 G^T W
    G`` (the normal matrix is ``D^T D + lam 2 G^T W G``) for the samples the problem was
    made with: a preconditioner, not differentiated.
    """

    hierarchy: Hierarchy
    samples: Array
    targets: Array
    level: Array
    cell: Array
    positions: Array
    data_diagonal: Array
    regulariser_diagonal: Array
    offset: Array
    eps: Array


def normal_matrices(
    hierarchy: Hierarchy, positions: ArrayLike, basis: ArrayLike | Callable[[], ArrayLike]
):
    """``(D, 2 G^T W G)`` as SciPy sparse matrices over the active functions, on the host:
    ``D = B M`` (rows the samples, ``B`` their ``4^d`` basis values at ``positions``,
    ``M`` the cascade matrix) and the regulariser's part of the normal matrix per unit
    lambda, so that ``D^T D + lam 2 G^T W G`` is the matrix of the normal equations.

    ``basis``: the samples' basis values, or a function that makes them. The regulariser
    is made first and ``basis`` asked for after it: the regulariser's products (its
    largest intermediates) and ``B`` with ``D`` are then never held at once, which was
    the assembly's peak (docs/performance.md, "A clean surface's hierarchy fit")."""
    from scipy import sparse

    cascaded = cascade_matrix(hierarchy)
    total = sum(hierarchy.level_sizes)
    regulariser = _regulariser_matrix(hierarchy, cascaded, total)
    positions = np.asarray(positions)
    basis = np.asarray(basis() if callable(basis) else basis)
    count, local = positions.shape
    index = np.int32 if count * local < 2**31 else np.int64  # one index type: no upcast copy
    # Each sample's row holds its 4^d distinct terms: CSR from the arrays as they are,
    # with no (row, column) pairs to sort and no copy of the entries.
    terms = sparse.csr_matrix(
        (basis.ravel(), positions.ravel(), np.arange(0, count * local + 1, local, dtype=index)),
        shape=(count, total),
    )
    del basis
    collocation = product_by_rows(terms, cascaded)
    return collocation, regulariser


def _regulariser_matrix(hierarchy: Hierarchy, cascaded, total: int):
    """``2 G^T W G`` (SciPy CSR) over the active functions, from the cascade matrix ``M``
    (``cascaded``, kept) over ``total`` relevant functions."""
    from scipy import sparse

    pairs, weights, start = [], [], 0
    for level in range(hierarchy.num_levels):
        pairs.append(np.asarray(hierarchy.edges[level]) + start)
        weights.append(np.asarray(hierarchy.edge_weights[level], float))
        start += hierarchy.level_sizes[level]
    pairs, weights = np.concatenate(pairs), np.concatenate(weights)
    edges = len(pairs)
    # R = 2 sum w (G a)^2 over the pairs' cascaded coefficients a = M c: lam R adds
    # lam * 2 G^T W G = lam M^T (2 G0^T W G0) M to the normal matrix, G0 the pairs'
    # differences. 2 G0^T W G0 is a graph Laplacian of a few entries a row, so M^T (L M)
    # is cheaper than G = G0 M and G^T G (G has a row a pair). G0's rows carry sqrt(2 w)
    # (the weights are positive): no weighted copy.
    root = np.sqrt(2.0 * weights)
    pair_differences = sparse.csr_matrix(
        (np.stack([root, -root], 1).ravel(), pairs.ravel(), np.arange(0, 2 * edges + 1, 2)),
        shape=(edges, total),
    )
    laplacian = sparse.csr_matrix(pair_differences.T @ pair_differences)
    del pair_differences
    smoothed = sparse.csr_matrix(laplacian @ cascaded)
    del laplacian
    # M^T as a CSR view of M in CSC: a product of two CSR matrices, with no conversion
    # of the (larger) L M or of the result.
    return product_by_rows(cascaded.tocsc().T, smoothed)


def problem_matrices(problem: AdaptiveProblem):
    """``normal_matrices`` of a laid-out ``problem``: ``(D, 2 G^T W G)`` from its samples'
    positions and basis values (the latter made after the regulariser)."""
    positions = np.asarray(problem.positions)
    return normal_matrices(problem.hierarchy, positions, lambda: sample_basis(problem))


#: Entries of D squared at a time in ``column_squares``.
SQUARED_CHUNK = 1 << 21


def column_squares(matrix, columns: int, row_weights=None) -> np.ndarray:
    """The column sums of a CSR matrix's squared entries, each row's weighted by its
    ``row_weights`` (None: 1): the diagonal of ``D^T S D``. ``SQUARED_CHUNK`` entries are
    squared at a time: a squared copy of D's entries would be the assembly's peak."""
    out = np.zeros(columns)
    weights = None if row_weights is None else np.asarray(row_weights, float)
    for begin in range(0, len(matrix.data), SQUARED_CHUNK):
        stop = min(begin + SQUARED_CHUNK, len(matrix.data))
        data = matrix.data[begin:stop]
        squares = data * data
        if weights is not None:  # each entry's row: the last row starting at or before it
            rows = np.searchsorted(matrix.indptr, np.arange(begin, stop), side="right") - 1
            squares *= weights[rows]
        out += np.bincount(matrix.indices[begin:stop], squares, minlength=columns)
    return out


def make_adaptive_problem(
    points: Float[ArrayLike, "m d"],
    normals: Float[ArrayLike, "m d"],
    *,
    offset: float,
    eps: float,
    lower: Float[ArrayLike, " d"],
    upper: Float[ArrayLike, " d"],
    base: tuple[int, ...],
    levels: int,
    band: int = 2,
    dtype=None,
) -> AdaptiveProblem:
    """The samples of eq. 4-5 for unit outward ``normals`` and a hierarchy of ``levels``
    refinements of ``base`` cells around them (``refine_near``, ``band`` cells wide at each
    level). Host work on concrete points."""
    problem, _ = assemble_adaptive_problem(
        points,
        normals,
        offset=offset,
        eps=eps,
        lower=lower,
        upper=upper,
        base=base,
        levels=levels,
        band=band,
        dtype=dtype,
    )
    return problem


def assemble_adaptive_problem(
    points: Float[ArrayLike, "m d"],
    normals: Float[ArrayLike, "m d"],
    *,
    offset: float,
    eps: float,
    lower: Float[ArrayLike, " d"],
    upper: Float[ArrayLike, " d"],
    base: tuple[int, ...],
    levels: int,
    band: int = 2,
    dtype=None,
    combine_refined: Callable[[list[np.ndarray]], list[np.ndarray]] | None = None,
) -> tuple[AdaptiveProblem, tuple]:
    """``(problem, (D, 2 G^T W G))``: ``make_adaptive_problem``'s problem and the host
    matrices of ``normal_matrices`` it was assembled from (its Jacobi diagonals come from
    them), so that a direct solve factorises them without assembling them again.

    ``combine_refined``: maps the cells these points ask to refine (``refine_near``: one
    sorted array of cell keys a level) to the cells the hierarchy refines; over several
    processes, the union of every process's (the same hierarchy in all), while each
    process's problem holds its own samples only. None: these points' own."""
    dtype = dtype or jnp.result_type(float)
    points_np = np.asarray(points, dtype=float)
    normals_np = np.asarray(normals, dtype=float)
    # All on the host (xp=np): a new cloud's structure compiles nothing (JAX's eager
    # operations would compile each of their shapes, about a hundred per new cloud).
    samples_np, targets_np = offset_samples(points_np, normals_np, offset, eps, xp=np)  # pyright: ignore[reportArgumentType]
    refine = refine_near(lower, upper, base, levels, samples_np, band)
    if combine_refined is not None:
        refine = combine_refined(refine)
    hierarchy = build_hierarchy(lower, upper, base, refine, dtype=dtype)
    samples_np = samples_np.astype(dtype)  # leaves found in the fit's own precision
    level, cell = locate_leaves(hierarchy, samples_np, xp=np)
    positions, local = leaf_terms(hierarchy, samples_np, level, cell, xp=np)
    collocation, regulariser = normal_matrices(
        hierarchy, positions, lambda: hierarchy_basis(local, xp=np)
    )
    data_diagonal = column_squares(collocation, hierarchy.num_active)
    regulariser_diagonal = regulariser.diagonal()
    problem = AdaptiveProblem(
        hierarchy=hierarchy,
        samples=on_device(samples_np),
        targets=on_device(targets_np, dtype),
        level=on_device(level),
        cell=on_device(cell),
        positions=on_device(positions),
        data_diagonal=on_device(data_diagonal, dtype),
        regulariser_diagonal=on_device(regulariser_diagonal, dtype),
        offset=on_device(offset, dtype),
        eps=on_device(eps, dtype),
    )
    return problem, (collocation, regulariser)


def at_points(
    problem: AdaptiveProblem, points: Float[Array, "m d"], normals: Float[Array, "m d"]
) -> AdaptiveProblem:
    """The problem with its samples moved to those of ``points`` and ``normals`` (traced
    or not), its leaves kept: for derivatives of a fit with respect to the data, each
    sample staying in its leaf (the fit is smooth there)."""
    samples, targets = offset_samples(points, normals, problem.offset, problem.eps)
    return eqx.tree_at(lambda p: (p.samples, p.targets), problem, (samples, targets))


def sample_basis(problem: AdaptiveProblem) -> Float[Array, "S k"]:
    """The ``4^d`` basis values at each sample in its leaf (differentiable in the
    samples)."""
    h = problem.hierarchy
    unit = (problem.samples - h.lower) / (h.upper - h.lower)
    sizes = jnp.stack([jnp.asarray(h.cells(lev), unit.dtype) for lev in range(h.num_levels)])
    t = unit * sizes[problem.level] - problem.cell.astype(unit.dtype)
    return hierarchy_basis(t)


def adaptive_values(
    problem: AdaptiveProblem, coeffs: Float[Array, "*lead n"], basis: Array | None = None
) -> Float[Array, "*lead S"]:
    """``D c``: the THB spline of ``coeffs`` at every sample (eq. 2 on the hierarchy)."""
    basis = sample_basis(problem) if basis is None else basis
    a = cascade(problem.hierarchy, coeffs)
    return jnp.sum(a[..., problem.positions] * basis, axis=-1)


def adaptive_objective(problem: AdaptiveProblem, coeffs: Array, lam, basis=None) -> Array:
    """``E_d + lam R`` (eq. 16 with w = 1, eq. 31 carried to the hierarchy by
    [`hierarchy_regulariser`][jurs.internal.hierarchy_regulariser])."""
    r = adaptive_values(problem, coeffs, basis) - problem.targets
    return jnp.sum(r * r) + lam * hierarchy_regulariser(problem.hierarchy, coeffs)


def adaptive_metrics(problem: AdaptiveProblem, coeffs: Array, lam, basis=None) -> dict:
    """``E``, ``E_d``, ``R``, ``E_ave``, ``E_max`` and ``lam`` of a fit on the hierarchy, as
    [`jurs.internal.metrics`][] gives them for a uniform fit (eq. 16, 31, 35-37):
    ``E_ave = mean g(P_i)^2`` and ``E_max = max |g(P_i)|`` over the m data points only
    (the first m samples, whose targets are 0), not over the offset samples."""
    r = adaptive_values(problem, coeffs, basis) - problem.targets
    reg = hierarchy_regulariser(problem.hierarchy, coeffs)
    m = problem.samples.shape[0] // 3
    on_data = r[:m]
    sums = dict(
        E_d=jnp.sum(r * r),
        on_data2=jnp.sum(on_data * on_data),
        count=m,
        E_max=jnp.max(jnp.abs(on_data)),
    )
    return dict(metrics_from_sums(sums, reg, lam), lam=jnp.asarray(lam, r.dtype))


def assembled_metrics(problem: AdaptiveProblem, matrices, coeffs, lam: float) -> dict:
    """``adaptive_metrics`` from the host matrices
    ``(D, 2 G^T W G)`` of ``assemble_adaptive_problem``: the same numbers with nothing
    compiled (``R = c^T (2 G^T W G) c``), for fits solved on the host."""
    collocation, regulariser = matrices
    c = np.asarray(coeffs, np.float64)
    r = collocation @ c - np.asarray(problem.targets, np.float64)
    m = problem.samples.shape[0] // 3
    on_data = r[:m]  # the data points' samples come first (targets 0)
    sums = dict(
        E_d=float(r @ r),
        on_data2=float(on_data @ on_data),
        count=m,
        E_max=float(np.max(np.abs(on_data))),
    )
    metrics = dict(metrics_from_sums(sums, float(c @ (regulariser @ c)), lam), lam=lam)
    return {name: on_device(value, problem.targets.dtype) for name, value in metrics.items()}


def normal_matvec(problem: AdaptiveProblem, lam, basis=None):
    """``c -> (D^T D + 2 lam G^T W G) c``, half the gradient of the objective's quadratic
    part: the matrix of the normal equations, never formed."""
    basis = sample_basis(problem) if basis is None else basis

    def quadratic(c):
        v = adaptive_values(problem, c, basis)
        return 0.5 * jnp.sum(v * v) + 0.5 * lam * hierarchy_regulariser(problem.hierarchy, c)

    return jax.grad(quadratic)


def normal_rhs(problem: AdaptiveProblem, basis=None) -> Array:
    """``D^T b``."""
    n = problem.hierarchy.num_active
    zero = jnp.zeros((n,), problem.targets.dtype)
    _, transpose = jax.vjp(lambda c: adaptive_values(problem, c, basis), zero)
    return transpose(problem.targets)[0]
