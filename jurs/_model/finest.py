"""A THB spline's coefficients on its finest uniform grid, computed only where asked.

On a leaf of level ``l`` the spline is the level-``l`` B-spline of its cascaded
coefficients (``jurs._model.hierarchy.cascade``); subdividing those ``finest - l`` times
gives the finest level's coefficients over that leaf. ``finest_coefficients`` does this
for the finest-grid functions a caller names (the band mesh's blocks, a lattice's nodes),
so a spline on a 1024^3-equivalent grid is read in pieces, on the host, with nothing
compiled and no finest-level array.
"""

from __future__ import annotations

import numpy as np
from jaxtyping import Float, Int

from .hierarchy import (
    SUBDIVISION,
    Hierarchy,
    cube_offsets,
    index_in,
    is_member,
    ravel_keys,
    unravel_keys,
)

#: Entries of the leaves' coefficients gathered at a time for the functions asked of
#: ``finest_coefficients`` (float64: 32 MiB).
TABLE_ENTRIES = 1 << 22


def subdivision_matrix(steps: int) -> np.ndarray:
    """The 1D coefficients of a cell's four cubic B-splines at a level ``steps`` finer:
    ``out[m, i]`` is the coefficient of the finer function ``c 2^steps + m`` in the coarse
    function ``c + i`` (functions numbered as in the hierarchy's function grid, cell ``c``
    covered by functions ``c .. c + 3``); ``(2^steps + 3, 4)``, host float64. The finer
    functions listed are those over the cell's subcells; a coarse function's terms on
    others never reach the cell."""
    out = np.eye(4)
    for _ in range(steps):
        size = out.shape[0]
        finer = np.zeros((2 * size - 3, 4))
        # Coarse r (relative to 2c at the finer level) -> finer 2r - 3 + k; keep the
        # functions over the subcells (relative 0 .. 2 size - 4).
        for r in range(size):
            for k in range(5):
                j = 2 * r - 3 + k
                if 0 <= j < finer.shape[0]:
                    finer[j] += SUBDIVISION[k] * out[r]
        out = finer
    return out


def _subdivided(values: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """Leaves' ``4^d`` coefficients ``values (k, u, 4, .., 4)`` carried to the finer level
    of ``matrix (S, 4)`` (``subdivision_matrix``): ``(k, u, S, .., S)``, one axis at a time,
    each entry four products added in a fixed order (element-wise, no BLAS), so an entry
    depends only on its leaf's values, never on the other leaves asked with it. The
    leaves run along the last axis meanwhile: each product then runs over a row of
    leaves, not over the few finer functions of one."""
    out = np.moveaxis(values, 1, -1)  # (k, 4, .., 4, u)
    for axis in range(1, values.ndim - 1):
        moved = np.moveaxis(out, axis, 0)  # (4, k, .., u)
        column = (-1,) + (1,) * (moved.ndim - 1)
        total = moved[0][None] * matrix[:, 0].reshape(column)
        for i in range(1, 4):
            total = total + moved[i][None] * matrix[:, i].reshape(column)
        out = np.moveaxis(total, 0, axis)
    return np.moveaxis(out, -1, 1)


def _subdivided_at(values: np.ndarray, matrix: np.ndarray, relative: np.ndarray) -> np.ndarray:
    """The finer coefficients asked of leaves: ``values (k, n, 4, .., 4)``, each asked
    function's leaf's ``4^d`` coefficients, carried to the finer function ``relative (n,
    d)`` of its leaf at the level of ``matrix (S, 4)`` (``subdivision_matrix``); ``(k,
    n)``. One axis at a time, each entry four products added in a fixed order
    (element-wise, no BLAS): an entry depends only on its leaf's values and its own
    index, never on what else is asked with it: bitwise ``_subdivided``'s entries, for
    the functions asked alone (``_asks_few``)."""
    out = values
    for axis in range(relative.shape[1]):
        weights = matrix[relative[:, axis]]  # (n, 4)
        column = (-1,) + (1,) * (out.ndim - 3)
        total = out[:, :, 0] * weights[:, 0].reshape(column)
        for i in range(1, 4):
            total = total + out[:, :, i] * weights[:, i].reshape(column)
        out = total
    return out


def _asks_few(asked: int, leaves: int, side: int, ndim: int) -> bool:
    """Whether ``asked`` functions of ``leaves`` leaves cost fewer products one by one
    (``_subdivided_at``: the leaf's ``4^d`` coefficients gathered, then ``4^d + ... + 4``
    products) than through the leaves' whole tables of ``side^d`` finer functions
    (``_subdivided``: ``4 side^j 4^(d - j)`` products for the axis j of d). A verdict's
    lattice of half cells asks a few functions of each leaf, a mesh's lattice most."""
    one_by_one = 4**ndim + sum(4 ** (j + 1) for j in range(ndim))
    table = 4**ndim + sum(4 * side**j * 4 ** (ndim - j) for j in range(1, ndim + 1))
    return asked * one_by_one < leaves * table


def level_offsets(hierarchy: Hierarchy) -> np.ndarray:
    """Where each level starts in the concatenated cascaded vector of
    [`cascade`][jurs.internal.cascade]; ``(levels + 1,)``."""
    return np.concatenate([[0], np.cumsum(hierarchy.level_sizes)]).astype(np.int64)


def finest_coefficients(
    hierarchy: Hierarchy, cascaded: Float[np.ndarray, "k s"], functions: Int[np.ndarray, "n d"]
) -> Float[np.ndarray, "k n"]:
    """The coefficients of THB splines in the finest level's *uniform* basis, for the
    given finest-level functions (multi-indices in the ``(n_L + 3)^d`` function grid;
    host NumPy).

    Every THB spline is a spline of the finest level (the levels' spaces nest), so over
    the whole box it has one coefficient per finest function. A function's coefficient
    follows from the spline's polynomial on any finest cell of its support: here the cell
    ``clip(j - 2, 0, n_L - 1)`` (its support's second cell), whose leaf of level ``l``
    carries the cascaded coefficients ``a^l``; ``L - l`` cubic subdivisions of the leaf's
    ``4^d`` of them give the coefficient (``subdivision_matrix``). On a finest leaf that
    is ``a^L_j`` itself.

    ``cascaded``: ``(k, s)`` from [`cascade`][jurs.internal.cascade] (``k`` splines).
    The subdivision runs axis by axis, per leaf over all ``(2^(L-l) + 3)^d`` finer
    functions of the leaf at once (about ``8 k`` operations a function), or where few of
    a level's are asked for each function alone from its leaf's ``4^d`` coefficients
    (``_asks_few``); either way in groups that bound the memory. Each coefficient is
    computed by the same element-wise operations in the same order whatever else is
    asked with it, so one function asked twice gets bitwise the same value: lattices
    evaluated from these coefficients agree on shared nodes to the bit.
    """
    cascaded = np.asarray(cascaded, np.float64)
    functions = np.asarray(functions, np.int64).reshape(-1, hierarchy.ndim)
    ndim = hierarchy.ndim
    finest = hierarchy.num_levels - 1
    cells = np.asarray(hierarchy.cells(finest), np.int64)
    functions = np.clip(functions, 0, cells + 2)
    reference = np.clip(functions - 2, 0, cells - 1)
    starts = level_offsets(hierarchy)
    level = np.full(len(functions), -1, np.int64)
    for lev in range(finest, -1, -1):
        leaves = np.asarray(hierarchy.leaf_keys[lev], np.int64)
        todo = np.flatnonzero(level < 0)
        if todo.size == 0 or leaves.size == 0:
            continue
        key = ravel_keys(reference[todo] >> (finest - lev), hierarchy.cells(lev))
        level[todo[is_member(key, leaves)]] = lev
    if np.any(level < 0):
        raise AssertionError("hierarchy: a finest cell lies in no leaf")
    out = np.zeros((cascaded.shape[0], len(functions)))
    corner = cube_offsets(ndim, 4)
    for lev in range(finest + 1):
        mine = np.flatnonzero(level == lev)
        if mine.size == 0:
            continue
        keys = np.asarray(hierarchy.function_keys[lev], np.int64)
        extent = hierarchy.functions(lev)
        steps = finest - lev
        if steps == 0:
            at = index_in(ravel_keys(functions[mine], extent), keys)
            out[:, mine] = cascaded[:, starts[lev] + at]
            continue
        leaf = reference[mine] >> steps
        unique, which = np.unique(ravel_keys(leaf, hierarchy.cells(lev)), return_inverse=True)
        leaf_cells = unravel_keys(unique, hierarchy.cells(lev))
        around = ravel_keys(leaf_cells[:, None, :] + corner[None], extent)  # (u, 4^d)
        values = cascaded[:, starts[lev] + index_in(around.ravel(), keys)].reshape(
            (cascaded.shape[0], len(unique)) + (4,) * ndim
        )
        relative = functions[mine] - (leaf << steps)  # in [0, 2^steps + 3)
        matrix = subdivision_matrix(steps)
        which = which.reshape(-1)
        if _asks_few(len(mine), len(unique), matrix.shape[0], ndim):
            group = max(1, TABLE_ENTRIES // (cascaded.shape[0] * 4**ndim))
            for lo in range(0, len(mine), group):
                picked = slice(lo, lo + group)
                out[:, mine[picked]] = _subdivided_at(
                    values[:, which[picked]], matrix, relative[picked]
                )
            continue
        group = max(1, TABLE_ENTRIES // (cascaded.shape[0] * matrix.shape[0] ** ndim))
        order = np.argsort(which, kind="stable")
        bounds = np.searchsorted(which[order], np.arange(0, len(unique) + group, group))
        for g, (lo, hi) in enumerate(zip(bounds[:-1], bounds[1:])):
            if lo == hi:
                continue
            picked = order[lo:hi]
            table = _subdivided(values[:, g * group : (g + 1) * group], matrix)
            index = (slice(None), which[picked] - g * group) + tuple(relative[picked].T)
            out[:, mine[picked]] = table[index]
    return out
