"""A THB spline at points: each point's leaf (the finest cell that holds it), the cascaded
coefficients of its ``4^d`` level functions there, and the values and gradients they give
(docs/design.md section 8, "Evaluation"). The structure comes from ``hierarchy.py``; the
lookups are sorted searches of integer keys, in NumPy on the host or in JAX (``xp``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float, Int

from .basis import cubic_derivatives, cubic_weights, tensor_basis
from .hierarchy import MAX_KEY, Hierarchy, cascade, cube_offsets


def locate_leaves(
    hierarchy: Hierarchy, x: Float[Array, "n d"] | Float[np.ndarray, "n d"], xp=jnp
) -> tuple[Int[Array, " n"], Int[Array, "n d"]]:
    """The level of each point's leaf and the leaf's cell (multi-index at that level).
    Points outside the box take the border leaf (the basis extrapolates there, as the
    uniform basis does). A sorted search per level; no finest-level array. ``xp=numpy``
    computes on the host (concrete points), compiling nothing."""
    level = xp.zeros(x.shape[0], xp.int32)
    cell = xp.zeros(x.shape, xp.int32)
    lower, upper = xp.asarray(hierarchy.lower), xp.asarray(hierarchy.upper)
    unit = (x - lower) / (upper - lower)
    for lev in range(hierarchy.num_levels):
        cells = hierarchy.cells(lev)
        top = xp.asarray(cells, xp.int32) - 1
        here = xp.clip(xp.floor(unit * xp.asarray(cells, unit.dtype)), 0, top).astype(xp.int32)
        key = _jnp_ravel(here, cells)
        keys = xp.asarray(hierarchy.leaf_keys[lev])
        if keys.shape[0] == 0:
            continue
        at = xp.clip(xp.searchsorted(keys, key), 0, keys.shape[0] - 1)
        found = keys[at] == key
        level = xp.where(found, lev, level)
        cell = xp.where(found[:, None], here, cell)
    return level, cell


def _jnp_ravel(index: Array, extent: tuple[int, ...]) -> Array:
    key = index[..., 0]
    for axis in range(1, len(extent)):
        key = key * extent[axis] + index[..., axis]
    return key


def leaf_terms(
    hierarchy: Hierarchy,
    x: Float[Array, "n d"] | Float[np.ndarray, "n d"],
    level: Int[Array, " n"] | Int[np.ndarray, " n"],
    cell: Int[Array, "n d"] | Int[np.ndarray, "n d"],
    xp=jnp,
) -> tuple[Int[Array, "n k"], Array]:
    """For points in the given leaves: the positions, in the cascaded vector of
    [`cascade`][jurs.internal.cascade], of the ``4^d`` functions over each leaf, and the
    local coordinates ``t (n, d)`` in the leaf. Differentiable in ``x`` through ``t``;
    ``xp=numpy`` computes on the host.

    One sorted search of ``4^(d-1)`` keys per point: every level's function keys, shifted
    past the previous levels' grids, form one sorted array whose positions are those of
    the cascaded vector. (A search per level would cost ``levels * 4^d`` per point.) The
    four functions along the last axis have consecutive keys, and all ``4^d`` functions
    over a leaf are relevant on its level, so the four stand at consecutive positions:
    the first is searched, the other three follow. Where the shifted keys would leave
    int32, a search per level it is."""
    ndim = hierarchy.ndim
    offsets = xp.asarray(cube_offsets(ndim, 4), xp.int32)
    # cube_offsets runs the last axis fastest: every fourth offset starts a row of four.
    firsts = offsets[::4]
    levels = hierarchy.num_levels
    grids = [int(np.prod(hierarchy.functions(lev))) for lev in range(levels)]
    shifts = np.concatenate([[0], np.cumsum(grids)[:-1]]).astype(np.int64)
    lower, upper = xp.asarray(hierarchy.lower), xp.asarray(hierarchy.upper)
    unit = (x - lower) / (upper - lower)
    cells = xp.asarray([hierarchy.cells(lev) for lev in range(levels)], unit.dtype)
    t = unit * cells[level] - cell.astype(unit.dtype)
    if int(shifts[-1]) + grids[-1] > MAX_KEY:
        return _leaf_positions_per_level(hierarchy, level, cell, offsets, xp), t
    combined = xp.concatenate(
        [xp.asarray(hierarchy.function_keys[lev]) + xp.int32(shifts[lev]) for lev in range(levels)]
    )
    extent = xp.asarray([hierarchy.functions(lev) for lev in range(levels)], xp.int32)[level]
    index = cell[:, None, :] + firsts[None]
    key = index[..., 0]
    for axis in range(1, ndim):
        key = key * extent[:, None, axis] + index[..., axis]
    key = key + xp.asarray(shifts, xp.int32)[level][:, None]
    first = xp.clip(xp.searchsorted(combined, key), 0, combined.shape[0] - 4)
    positions = (first[:, :, None] + xp.arange(4, dtype=first.dtype)).reshape(-1, 4**ndim)
    return positions.astype(xp.int32), t


def _leaf_positions_per_level(hierarchy: Hierarchy, level, cell, offsets, xp=jnp) -> Array:
    """``leaf_terms``' positions by one sorted search per level (keys beyond int32)."""
    positions = xp.zeros((cell.shape[0], offsets.shape[0]), xp.int32)
    start = 0
    for lev in range(hierarchy.num_levels):
        extent = hierarchy.functions(lev)
        keys = xp.asarray(hierarchy.function_keys[lev])
        key = _jnp_ravel(cell[:, None, :] + offsets[None], extent)
        at = xp.clip(xp.searchsorted(keys, key), 0, keys.shape[0] - 1) + start
        positions = xp.where((level == lev)[:, None], at, positions)
        start += hierarchy.level_sizes[lev]
    return positions


def hierarchy_basis(t: Float[Array, "n d"], xp=jnp) -> Float[Array, "n k"]:
    """The ``4^d`` tensor-product cubic values at local coordinates ``t``, in the order of
    [`leaf_terms`][jurs.internal.leaf_terms]'s positions."""
    return tensor_basis(*(cubic_weights(t[:, a], xp=xp) for a in range(t.shape[1])))


# The traced evaluators (concrete splines evaluate on the host: AdaptiveSpline) are each
# one compiled program a hierarchy and point count. Run op by op, the leaf search and the
# cascade compile each of their few dozen operations for every new shape (a first gradient
# took over three times as long; docs/performance.md), and a warm call is several times
# slower.
@jax.jit
def hierarchy_values(
    hierarchy: Hierarchy, coeffs: Float[Array, "*lead n"], x: Float[Array, "m d"]
) -> Float[Array, "*lead m"]:
    """The THB spline ``sum_tau coeffs_tau tau(x)`` at points ``x``; pure JAX, jittable.
    Leading axes of ``coeffs`` evaluate several splines at once."""
    level, cell = locate_leaves(hierarchy, x)
    positions, t = leaf_terms(hierarchy, x, level, cell)
    a = cascade(hierarchy, coeffs)
    return jnp.sum(a[..., positions] * hierarchy_basis(t), axis=-1)


@jax.jit
def hierarchy_gradient(
    hierarchy: Hierarchy, coeffs: Float[Array, " n"], x: Float[Array, "m d"]
) -> Float[Array, "m d"]:
    """The gradient of the THB spline at ``x``, ``(m, d)``, from the leaves' local
    pieces (the spline is C^2, so the side of a leaf boundary does not matter)."""
    return hierarchy_values_and_gradients(hierarchy, coeffs, x)[1]


@jax.jit
def hierarchy_values_and_gradients(
    hierarchy: Hierarchy, coeffs: Float[Array, "*lead n"], x: Float[Array, "m d"]
) -> tuple[Float[Array, "*lead m"], Float[Array, "*lead m d"]]:
    """The THB spline's values ``(*lead, m)`` and gradients ``(*lead, m, d)`` at ``x``,
    each leading axis of ``coeffs`` a spline: one leaf search and one cascade for all of
    them (a rational spline's numerator and denominator share both)."""
    level, cell = locate_leaves(hierarchy, x)
    positions, t = leaf_terms(hierarchy, x, level, cell)
    a = cascade(hierarchy, coeffs)[..., positions]
    widths = jnp.stack([hierarchy.cell_width(lev) for lev in range(hierarchy.num_levels)])[level]
    return local_values_and_gradients(a, t, widths)


def local_values_and_gradients(
    a: Float[Array, "*lead m k"], t: Float[Array, "m d"], widths: Float[Array, "m d"]
) -> tuple[Float[Array, "*lead m"], Float[Array, "*lead m d"]]:
    """Values and spatial gradients of the tensor-product cubic pieces with coefficients
    ``a`` (the ``4^d`` over each point's leaf, in ``hierarchy_basis``'s order) at local
    coordinates ``t`` in leaves of ``widths``."""
    ndim = t.shape[1]
    values = [cubic_weights(t[:, k]) for k in range(ndim)]
    slopes = [cubic_derivatives(t[:, k]) for k in range(ndim)]
    out = []
    for k in range(ndim):
        axes = [slopes[j] if j == k else values[j] for j in range(ndim)]
        out.append(jnp.sum(a * tensor_basis(*axes), axis=-1) / widths[:, k])
    return jnp.sum(a * tensor_basis(*values), axis=-1), jnp.stack(out, axis=-1)


def rational_values_and_gradients(
    both: Float[Array, "2 m"], slopes: Float[Array, "2 m d"]
) -> tuple[Float[Array, " m"], Float[Array, "m d"]]:
    """g = N / D (eq. 14) and its gradient by the quotient rule, from the stacked values
    ``both = (N, D)`` and gradients ``slopes`` of numerator and denominator."""
    g = both[0] / both[1]
    return g, (slopes[0] - g[:, None] * slopes[1]) / both[1][:, None]
