"""Coarser grids of a cubic B-spline coefficient grid, and the maps between grids.

One rule makes every coarser grid of the package, the multigrid's levels
(``jurs._linalg.multigrid``) and the cascadic start's
(``jurs.solvers._cascade``): an axis of ``n`` basis functions (``n - 3`` cells) becomes
``n // 2 + 2`` functions, cells twice as wide (``coarse_size``), and a sequence of
grids coarsens every axis at once until one is small enough (``coarsening``). The two
users differ in where they stop and in how the coarse grid sits on the box, hence in the
transfer:

* **Nested grids (multigrid).** The coarse cells are exactly twice the fine ones from the
  same lower end; with an odd number of fine cells the coarse box reaches one fine cell
  past the fine one. The coarse spline space then lies inside the fine one (knot
  insertion), and the subdivision mask ``(1, 4, 6, 4, 1) / 8`` writes coarse function
  ``I`` in the fine ones: ``B^c_I = sum_a mask[a] B_{2I - 3 + a}``. That matrix P is the
  exact prolongation (``prolong``), its transpose the restriction (``restrict``),
  and ``P^T A P`` the Galerkin coarse operator (``galerkin``). No coarse function
  vanishes on the fine box, so P keeps full column rank and every axis coarsens whatever
  its parity.
* **Re-fitted grids (cascade).** Each coarse grid spans the same box as the fine one (the
  same fit, solved again on fewer functions), so the spaces are not nested; a coarse
  solution reaches the next grid by its values at the fine grid's Greville points
  (``greville_transfer``, a quasi-interpolant accurate to O(h^2)).

Every map works axis by axis, for grids of any dimension d; stencils are the
``grid_shape + (7,) * d`` arrays of ``jurs._linalg.stencil``.
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .._model.basis import cubic_weights
from .stencil import HALF, SIDE, stencil_ndim

#: Uniform cubic B-spline subdivision mask: coarse function ``I`` is ``sum_a MASK[a]`` times
#: fine function ``2 I - 3 + a``.
MASK = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 8.0
#: Axes with fewer basis functions than this are not coarsened by the multigrid: below it
#: the multigrid's levels keep an axis whole (the cascade passes its own minimum, 4: every
#: axis that still shrinks).
MIN_COARSEN_SIDE = 8


def coarse_size(n: int, min_side: int = MIN_COARSEN_SIDE) -> int:
    """Basis functions along an axis after one coarsening: ``n // 2 + 2`` (cells
    ``ceil((n - 3) / 2)``), or ``n`` for axes below ``min_side``."""
    return n // 2 + 2 if n >= min_side else n


def coarsening(shape: tuple[int, ...], max_size: int, min_side: int = MIN_COARSEN_SIDE) -> list:
    """The grid shapes from ``shape`` down, finest first (``shape`` itself included): every
    axis coarsened by ``coarse_size`` at once, until a grid has at most ``max_size``
    coefficients or no axis shrinks."""
    shapes = [tuple(int(n) for n in shape)]
    while np.prod(shapes[-1]) > max_size:
        coarse = tuple(coarse_size(n, min_side) for n in shapes[-1])
        if coarse == shapes[-1]:
            break
        shapes.append(coarse)
    return shapes


def _fine_windows(x: Array, axis: int, n_coarse: int) -> list:
    """The five arrays ``x[2 I - 3 + a]`` along ``axis`` (``a = 0..4``, ``I < n_coarse``), zero
    where the fine index is off the grid. One padded copy of ``x``, sliced five times:
    slicing the rows and padding each window instead makes XLA keep all five windows
    (docs/multigrid.md, "Measurements behind the constants")."""
    pad = [(0, 0)] * x.ndim
    pad[axis] = (3, 4)
    padded = jnp.pad(x, pad)
    return [
        jax.lax.slice_in_dim(padded, a, a + 2 * n_coarse - 1, stride=2, axis=axis)
        for a in range(MASK.size)
    ]


def restrict(grid: Array, coarse_shape: tuple[int, ...]) -> Array:
    """``P^T grid``: the fine residual's moments against the coarse basis functions of the
    nested grid ``coarse_shape``."""
    for axis, n_coarse in enumerate(coarse_shape):
        if n_coarse != grid.shape[axis]:
            windows = _fine_windows(grid, axis, n_coarse)
            grid = sum(float(w) * x for w, x in zip(MASK, windows))  # pyright: ignore[reportAssignmentType]
    return grid


def prolong(coarse: Array, fine_shape: tuple[int, ...]) -> Array:
    """``P coarse``: the nested coarse spline's coefficients in the fine basis (knot
    insertion); the transpose of ``restrict``."""
    fine = jax.ShapeDtypeStruct(tuple(fine_shape), coarse.dtype)
    (out,) = jax.linear_transpose(lambda g: restrict(g, coarse.shape), fine)(coarse)
    return out


def _galerkin_weights() -> np.ndarray:
    """``W[a, e, D] = MASK[a] MASK[a + (e - 3) - 2 (D - 3)]`` (0 off the mask): coarse
    ``A_c[I, I + D - 3]`` sums ``W[a, e, D] A[2 I - 3 + a, e]`` over the fine row's window
    ``a`` and stencil offset ``e``."""
    out = np.zeros((MASK.size, SIDE, SIDE))
    for a, e, d in itertools.product(range(MASK.size), range(SIDE), range(SIDE)):
        k = a + (e - HALF) - 2 * (d - HALF)
        if 0 <= k < MASK.size:
            out[a, e, d] = MASK[a] * MASK[k]
    return out


def galerkin(stencil: Array, coarse_shape: tuple[int, ...]) -> Array:
    """The stencil of ``P^T A P`` on the nested grid ``coarse_shape`` (one axis at a time;
    P is a tensor product). Coarse functions couple within 3 of each other, as fine ones
    do. Each coarse offset is one weighted sum of fine slices, which XLA fuses into a
    single pass; ``tensordot`` contractions instead need temporaries several times the
    stencil's size (docs/multigrid.md, "Measurements behind the constants")."""
    d = stencil_ndim(stencil)
    weights = _galerkin_weights()
    for axis, n_coarse in enumerate(coarse_shape):
        if n_coarse == stencil.shape[axis]:
            continue
        windows = _fine_windows(stencil, axis, n_coarse)
        offsets = []
        for coarse_offset in range(SIDE):
            offsets.append(
                sum(
                    float(weights[a, e, coarse_offset])
                    * jax.lax.index_in_dim(windows[a], e, axis=d + axis, keepdims=False)
                    for a in range(MASK.size)
                    for e in range(SIDE)
                    if weights[a, e, coarse_offset] != 0.0
                )
            )
        out = jnp.stack(offsets, axis=d + axis)
        # Entries towards coarse functions off the grid: zero (they are, up to rounding).
        index = np.arange(n_coarse)[:, None] + np.arange(SIDE)[None, :] - HALF
        valid = (index >= 0) & (index < n_coarse)
        shape = [1] * out.ndim
        shape[axis], shape[d + axis] = n_coarse, SIDE
        stencil = jnp.where(jnp.asarray(valid.reshape(shape)), out, 0.0)
    return stencil


def greville_matrix(coarse: int, fine: int) -> np.ndarray:
    """``(fine, coarse)``: the coarse cubic B-splines of one axis at the fine grid's Greville
    points, both grids spanning the same box (in units of the coarse cell, the box is
    ``[0, coarse - 3]``)."""
    u = (np.arange(fine) - 1.0) * (coarse - 3) / (fine - 3)
    cell = np.clip(np.floor(u), 0, coarse - 4).astype(int)
    values = cubic_weights(u - cell, xp=np)  # (fine, 4)
    out = np.zeros((fine, coarse))
    for a in range(4):
        out[np.arange(fine), cell + a] += values[:, a]
    return out


def greville_transfer(grid: Array, shape: tuple[int, ...]) -> Array:
    """A coefficient grid's spline, quasi-interpolated on the grid of ``shape`` over the same
    box (one matrix product an axis, ``greville_matrix``)."""
    for axis, n in enumerate(shape):
        matrix = jnp.asarray(greville_matrix(grid.shape[axis], n), grid.dtype)
        grid = jnp.moveaxis(jnp.tensordot(matrix, grid, axes=[[1], [axis]]), 0, axis)
    return grid
