"""Banded systems on coefficient grids stored as stencils, and their lineax operator type.

Two cubic B-splines of a uniform grid overlap only when they are at most 3 apart along
every axis, so the matrices of the exact solve (``D^T D``, the Laplacian L of the
regulariser, their sums and Galerkin products) are banded: row ``p`` of the grid couples to
``p + e`` for ``|e_k| <= 3``. Such a matrix on a grid of dimension d is stored as a
**stencil**, an array ``grid_shape + (7,) * d`` with ``stencil[p, 3 + e] = A[p, p + e]``
(zero towards points off the grid): 49 numbers a row in 2D, 343 in 3D. This module holds
the stencil maths (product, diagonal, Laplacian, conversion to dense and SciPy matrices,
probing a stencil from a matrix-vector product) and ``StencilOperator``, a stencil as
a lineax operator (``jurs._linalg.operator.AbstractGridOperator``).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .operator import AbstractGridOperator
from .spd import spd_inverse

if TYPE_CHECKING:  # SciPy loads when a stencil is converted, not on import
    import scipy.sparse
    from jax.typing import DTypeLike

#: Half-width of the stencil: cubic basis functions ``i`` and ``i + 3`` still share a cell.
HALF = 3
#: Stencil side, ``2 * HALF + 1``.
SIDE = 7


def _offsets(ndim: int):
    """All stencil offsets of a ``ndim``-dimensional grid, as index tuples into the stencil's
    trailing ``(7,) * ndim`` axes (``HALF`` is offset 0)."""
    return itertools.product(range(SIDE), repeat=ndim)


def stencil_ndim(stencil: Array | np.ndarray) -> int:
    """The grid dimension d of a ``grid_shape + (7,) * d`` stencil."""
    d, odd = divmod(stencil.ndim, 2)
    if odd or stencil.shape[d:] != (SIDE,) * d:
        raise ValueError(f"stencil must be shaped grid_shape + (7,) * d, got {stencil.shape}")
    return d


def laplacian_stencil(shape: tuple[int, ...], dtype: DTypeLike = float) -> Array:
    """The grid Laplacian L of [`jurs.internal.grid_laplacian`][] (free boundary) as a
    stencil, for a grid of any dimension d: degree at the centre, -1 towards each existing
    one of the ``2 d`` axis neighbours."""
    d = len(shape)
    return plus_laplacian(jnp.zeros(tuple(shape) + (SIDE,) * d, dtype), 1.0)


def plus_laplacian(stencil: Array, scale) -> Array:
    """``stencil + scale * laplacian_stencil(...)`` for a ``grid_shape + (7,) * d``
    stencil, the Laplacian's ``2 d + 1`` entries a coefficient added where they sit: no
    stencil-sized array of the Laplacian, mostly zeros, which XLA would otherwise make
    (and, in a loop of solves such as a robust fit's, hoist out and hold throughout: a
    third of a 48^3 robust fit's working memory)."""
    d = stencil.ndim // 2
    shape = stencil.shape[:d]
    dtype = stencil.dtype
    centre = (HALF,) * d
    degree = jnp.zeros(shape, dtype)
    for axis, n in enumerate(shape):
        index = jnp.arange(n).reshape((n,) + (1,) * (d - 1 - axis))
        for step, exists in ((-1, index > 0), (1, index < n - 1)):
            exists = jnp.broadcast_to(exists, shape).astype(dtype)
            offset: list[int] = list(centre)
            offset[axis] += step
            stencil = stencil.at[(Ellipsis, *offset)].add(scale * -exists)
            degree = degree + exists
    return stencil.at[(Ellipsis, *centre)].add(scale * degree)


@jax.custom_jvp
def stencil_matvec(stencil: Array, grid: Array) -> Array:
    """Apply a ``grid_shape + (7,) * d`` stencil to a ``grid_shape`` grid (zero outside the
    grid), for any grid dimension d (49 terms in 2D, 343 in 3D).

    A sum of shifted products (a grid's worth of memory). Its derivatives are
    ``_window_matvec`` (a stencil's worth of memory, as the stencil itself): the sum's own,
    transposed for reverse mode, set each of its 343 slices into a zero array of the
    stencil's (or padded grid's) size, and compiling ``jax.grad`` through a 3D fit took
    minutes instead of seconds (docs/performance.md, "Measurements behind the defaults")."""
    d = grid.ndim
    padded = jnp.pad(grid, HALF)
    out = jnp.zeros_like(grid)
    for offset in _offsets(d):
        window = tuple(slice(o, o + n) for o, n in zip(offset, grid.shape))
        out = out + stencil[(Ellipsis, *offset)] * padded[window]
    return out


def _windows(grid: Array) -> Array:
    """``(7^d,) + grid_shape``: the grid's values at every stencil offset of each point (0
    off the grid), offsets in ``_offsets`` order."""
    d = grid.ndim
    patches = jax.lax.conv_general_dilated_patches(
        grid[None, None],
        (SIDE,) * d,
        (1,) * d,
        [(HALF, HALF)] * d,
        precision=jax.lax.Precision.HIGHEST,  # copies of the values, not TF32-rounded ones
    )
    return patches[0]


def _window_matvec(stencil: Array, grid: Array) -> Array:
    """``stencil_matvec`` as one contraction of the stencil with ``_windows`` (a stencil's
    worth of memory): linear in the stencil, and its transpose there is one product."""
    flat = stencil.reshape(grid.shape + (SIDE**grid.ndim,))
    return jnp.sum(flat * jnp.moveaxis(_windows(grid), 0, -1), axis=-1)


def _stencil_matvec_jvp(primals, tangents):
    stencil, grid = primals
    d_stencil, d_grid = tangents
    out = stencil_matvec(stencil, grid)
    tangent = jnp.zeros_like(out)
    if not isinstance(d_stencil, jax.custom_derivatives.SymbolicZero):
        tangent = tangent + _window_matvec(d_stencil, grid)
    if not isinstance(d_grid, jax.custom_derivatives.SymbolicZero):
        tangent = tangent + _window_matvec(stencil, d_grid)
    return out, tangent


stencil_matvec.defjvp(_stencil_matvec_jvp, symbolic_zeros=True)


def stencil_diagonal(stencil: Array) -> Array:
    """The diagonal of the matrix a stencil stands for, as a grid."""
    return stencil[(Ellipsis,) + (HALF,) * stencil_ndim(stencil)]


def _stencil_indices(shape: tuple[int, ...]):
    """``(row, col, valid)`` of every stencil entry (NumPy, shaped like the stencil): the
    matrix position of entry ``[i, 3 + di]`` is ``(flat(i), flat(i + di))``, valid where
    ``i + di`` is on the grid (row-major flattening)."""
    d = len(shape)
    grids = np.meshgrid(
        *[np.arange(n) for n in shape], *[np.arange(SIDE) - HALF] * d, indexing="ij"
    )
    points, steps = grids[:d], grids[d:]
    targets = [p + s for p, s in zip(points, steps)]
    valid = np.all([(t >= 0) & (t < n) for t, n in zip(targets, shape)], axis=0)
    row = np.ravel_multi_index(points, shape)
    col = np.ravel_multi_index([np.clip(t, 0, n - 1) for t, n in zip(targets, shape)], shape)
    return row, col, valid


def stencil_to_dense(stencil: Array) -> Array:
    """The dense ``n x n`` matrix of a stencil (``n`` grid points, row-major flattening),
    for direct solves on small grids: 7^d of each row's ``n`` entries are non-zero."""
    shape = stencil.shape[: stencil_ndim(stencil)]
    row, col, valid = _stencil_indices(shape)
    size = int(np.prod(shape))
    # Out-of-grid entries are 0 in the stencil; they are added (as 0) to a clipped column.
    values = jnp.where(jnp.asarray(valid), stencil, 0.0)
    return jnp.zeros((size, size), stencil.dtype).at[row.ravel(), col.ravel()].add(values.ravel())


def stencil_to_scipy(stencil) -> scipy.sparse.csr_matrix:
    """The stencil as a SciPy CSR matrix (NumPy side, for inspection or SciPy solvers)."""
    import scipy.sparse as sp

    s = np.asarray(stencil)
    shape = s.shape[: stencil_ndim(s)]
    row, col, valid = _stencil_indices(shape)
    keep = valid & (s != 0)
    size = int(np.prod(shape))
    return sp.csr_matrix((s[keep], (row[keep], col[keep])), shape=(size, size))


def probe_stencil(matvec, shape: tuple[int, ...], dtype) -> Array:
    """The stencil of a linear map on a grid that couples points at most 3 apart along
    every axis, from ``7^d`` products with colour-class indicators: point ``q`` is in class
    ``q mod 7``, and ``(A v_c)[p]`` is the one entry ``A[p, q]`` with ``q`` in class c."""
    d = len(shape)
    index = np.indices(shape)
    classes = list(itertools.product(range(SIDE), repeat=d))
    probes = np.stack(
        [np.all([index[k] % SIDE == c[k] for k in range(d)], axis=0) for c in classes]
    ).astype(dtype)
    products = jax.lax.map(matvec, jnp.asarray(probes))  # (7^d,) + shape
    entries = []
    for offset in itertools.product(range(SIDE), repeat=d):
        target = [(index[k] + offset[k] - HALF) % SIDE for k in range(d)]
        which = np.ravel_multi_index(target, (SIDE,) * d)
        entries.append(jnp.take_along_axis(products, jnp.asarray(which)[None], axis=0)[0])
    return jnp.stack(entries, axis=-1).reshape(tuple(shape) + (SIDE,) * d)


#: Side of the blocks of ``BlockJacobi``: 2^d neighbouring coefficients a block. On a 3D
#: surface fit it took CG about half the steps of Jacobi's at a few per cent more a step;
#: blocks of 3^3 and 4^3 saved few steps more (docs/multigrid.md, "Measurements behind the
#: constants").
BLOCK_SIDE = 2
#: Ridge added to each block scaled to a unit diagonal before it is inverted
#: (``jurs._linalg.spd.spd_inverse``: no LAPACK): a block can be singular where the
#: regulariser is off (``lam = 0``) and the samples leave a combination of its functions
#: unseen; the ridge bounds the preconditioner there and is far below a determined block's
#: eigenvalues elsewhere. At least ``100 eps`` of the dtype.
BLOCK_RIDGE = 1e-6


class BlockJacobi(eqx.Module):
    """The inverses of a stencil's diagonal blocks, each ``BLOCK_SIDE^d`` neighbouring
    coefficients (the grid cut into such blocks from its first point, padded with identity
    rows to a whole number of them), as a preconditioner: ``BlockJacobi(stencil)(r)``.

    Neighbouring cubic B-splines overlap most of their supports, so a normal-equation
    matrix couples each coefficient strongly to its neighbours: the diagonal alone (Jacobi)
    leaves those couplings to CG, a block's inverse resolves them. Symmetric positive
    definite (a block is inverted scaled to a unit diagonal, plus ``BLOCK_RIDGE``; a
    zero row as an identity row). Memory: ``BLOCK_SIDE^d`` numbers a coefficient."""

    inverses: Array  # block grid + (k, k), k = BLOCK_SIDE^d
    shape: tuple[int, ...] = eqx.field(static=True)  # the coefficient grid's

    def __init__(self, stencil: Array):
        d = stencil_ndim(stencil)
        shape = stencil.shape[:d]
        side = BLOCK_SIDE
        blocks = tuple(-(-n // side) for n in shape)
        members = list(itertools.product(range(side), repeat=d))
        rows = []
        for a in members:  # member a of block B is point side B + a
            # Strided slices of the stencil, padded (zero couplings) to the block grid: a
            # padded copy of the whole stencil would be the largest array of the solve.
            points = tuple(slice(e, None, side) for e in a)
            row = []
            for b in members:
                entries = stencil[points + tuple(HALF + eb - ea for ea, eb in zip(a, b))]
                row.append(jnp.pad(entries, [(0, n - m) for n, m in zip(blocks, entries.shape)]))
            rows.append(jnp.stack(row, axis=-1))
        matrix = jnp.stack(rows, axis=-2)  # blocks + (k, k)
        # Padded points (all couplings 0) become identity rows.
        ridge = max(BLOCK_RIDGE, 100 * float(jnp.finfo(matrix.dtype).eps))
        self.inverses = spd_inverse(matrix, ridge)
        self.shape = tuple(shape)

    def __call__(self, grid: Array) -> Array:
        d, side = len(self.shape), BLOCK_SIDE
        blocks = self.inverses.shape[:d]
        pad = [(0, b * side - n) for b, n in zip(blocks, self.shape)]
        split = jnp.pad(grid, pad).reshape(sum(((b, side) for b in blocks), ()))
        # (b_0, s, b_1, s, ...) -> (b_0, b_1, ..., s, s, ...): a block's members last.
        order = tuple(range(0, 2 * d, 2)) + tuple(range(1, 2 * d, 2))
        flat = jnp.transpose(split, order).reshape(blocks + (side**d,))
        solved = jnp.einsum("...ij,...j->...i", self.inverses, flat)
        back = jnp.transpose(solved.reshape(blocks + (side,) * d), tuple(np.argsort(order)))
        out = back.reshape(tuple(b * side for b in blocks))
        return out[tuple(slice(0, n) for n in self.shape)]


class StencilOperator(AbstractGridOperator):
    """A symmetric positive semi-definite matrix on a coefficient grid, stored as its
    ``grid_shape + (7,) * d`` stencil (any grid dimension d), as a lineax operator.

    ``mv`` is ``stencil_matvec`` (O(grid) work), ``as_matrix`` ``stencil_to_dense``
    (for dense solves of small grids). The stencil must be that of a symmetric positive
    semi-definite matrix (a normal-equation matrix ``D^T D + 2 lam L`` is); it is not
    checked. Solvers that use the stencil itself recognise this type:
    ``jurs._linalg.multigrid.Multigrid`` and
    ``jurs._linalg.cholesky.BlockCholesky``.
    """

    stencil: Array

    def __check_init__(self):
        stencil_ndim(self.stencil)

    def mv(self, vector: Array) -> Array:
        return stencil_matvec(self.stencil, vector)

    def as_matrix(self) -> Array:
        return stencil_to_dense(self.stencil)

    def in_structure(self) -> jax.ShapeDtypeStruct:
        shape = self.stencil.shape[: stencil_ndim(self.stencil)]
        return jax.ShapeDtypeStruct(shape, self.stencil.dtype)

    def grid_diagonal(self) -> Array:
        return stencil_diagonal(self.stencil)

    def with_grid_diagonal(self, diagonal: Array) -> StencilOperator:
        centre = (Ellipsis,) + (HALF,) * stencil_ndim(self.stencil)
        return StencilOperator(self.stencil.at[centre].set(diagonal))

    def preconditioner(self) -> Callable[[Array], Array]:
        """Block Jacobi (``BlockJacobi``) on a 3D grid; Jacobi in 2D, where CG runs only
        when ``lam = 0`` or on grids too large for the block Cholesky, and its early stop
        is part of the answer (``jurs.LeastSquares``'s ``ridge``)."""
        if stencil_ndim(self.stencil) == 3:
            return BlockJacobi(self.stencil)
        return super().preconditioner()
