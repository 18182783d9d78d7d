"""A fitting problem on a THB hierarchy (``jurs._model.hierarchy``): the samples of eq. 4-5,
their leaves, and the energy ``E_d + lam R`` (eq. 16, 31) over the active functions.

The data term reads ``g(x_k) = sum_j B_j(t_k) a[p_kj]`` (``a`` the cascaded coefficients,
``p_kj`` the ``4^d`` functions over sample k's leaf): one gather per sample, whose
transpose is one scatter. Which leaf holds a sample is structure, found on the host once;
the local coordinates ``t_k`` are computed from the samples in JAX, so a loss through a fit
differentiates with respect to the points.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Float

from .._model.hierarchy import (
    Hierarchy,
    _unravel,
    build_hierarchy,
    cascade,
    hierarchy_basis,
    hierarchy_regulariser,
    leaf_terms,
    locate_leaves,
    refine_near,
)
from .problem import offset_samples


class AdaptiveProblem(eqx.Module):
    """Samples, targets and their leaves on a THB hierarchy.

    ``samples (S, d)`` and ``targets (S,)`` are eq. 4-5's (``[P, P + d n, P - d n]``);
    ``positions (S, 4^d)`` index the cascaded coefficients over each sample's leaf and
    ``cell (S, d)``, ``level (S,)`` name the leaf; ``colours (n,)`` group the active
    functions into sets with pairwise disjoint supports (see
    [`adaptive_diagonal`][jurs.internal.adaptive_diagonal]), ``num_colours`` static.
    """

    hierarchy: Hierarchy
    samples: Array
    targets: Array
    level: Array
    cell: Array
    positions: Array
    colours: Array
    offset: Array
    eps: Array
    num_colours: int = eqx.field(static=True)


def _colours(hierarchy: Hierarchy) -> tuple[np.ndarray, int]:
    """A colour per active function: its level and its index mod 4 along each axis. Two
    functions of one level whose indices differ by 4 or more along an axis have disjoint
    supports (a cubic spans 4 cells), truncation only shrinks supports, and levels get
    their own colours, so functions of one colour never overlap."""
    ndim = hierarchy.ndim
    out = []
    for level in range(hierarchy.num_levels):
        keys = np.asarray(hierarchy.function_keys[level])[np.asarray(hierarchy.active[level])]
        multi = _unravel(keys, hierarchy.functions(level)) % 4
        colour = level * 4**ndim + (multi * (4 ** np.arange(ndim))).sum(-1)
        out.append(colour)
    return np.concatenate(out).astype(np.int32), hierarchy.num_levels * 4**ndim


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
    dtype = dtype or jnp.result_type(float)
    points_np = np.asarray(points, dtype=float)
    normals_np = np.asarray(normals, dtype=float)
    # Host arrays through the same function (xp=np), for the structure only.
    samples_np, _ = offset_samples(points_np, normals_np, offset, eps, xp=np)  # pyright: ignore[reportArgumentType]
    refine = refine_near(lower, upper, base, levels, samples_np, band)
    hierarchy = build_hierarchy(lower, upper, base, refine, dtype=dtype)
    samples, targets = offset_samples(
        jnp.asarray(points, dtype), jnp.asarray(normals, dtype), offset, eps
    )
    level, cell = locate_leaves(hierarchy, jnp.asarray(samples_np, dtype))
    positions, _ = leaf_terms(hierarchy, samples, level, cell)
    colours, count = _colours(hierarchy)
    return AdaptiveProblem(
        hierarchy=hierarchy,
        samples=samples,
        targets=targets,
        level=level,
        cell=cell,
        positions=positions,
        colours=jnp.asarray(colours),
        offset=jnp.asarray(offset, dtype),
        eps=jnp.asarray(eps, dtype),
        num_colours=count,
    )


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


def adaptive_diagonal(problem: AdaptiveProblem, matvec) -> Float[Array, " n"]:
    """The exact diagonal of the normal matrix by probing: for each colour (functions with
    pairwise disjoint supports), ``A 1_colour`` equals ``A_tt`` at every function ``t`` of
    the colour, since ``A_ts = 0`` when supports do not overlap. ``num_colours`` matrix
    products (``levels * 4^d``), run as one batched product."""
    colours = jnp.arange(problem.num_colours)
    probes = (problem.colours[None, :] == colours[:, None]).astype(problem.targets.dtype)
    products = jax.vmap(matvec)(probes)
    return jnp.sum(products * probes, axis=0)
