"""The normal equations of the collocation least-squares problem, without forming D.

For fixed weights the data energy ``E_d = ||D C - b||^2`` is quadratic in C, and its
minimiser (with the regulariser of eq. 31) solves ``(D^T D + 2 lam L) C = D^T b``
(docs/design.md section 3). ``D^T D`` is banded: coefficient ``(i, j)`` couples only to
``(i + di, j + dj)`` with ``|di|, |dj| <= 3`` (two cubic basis functions overlap when
their supports share a cell), so it is stored as an ``(N, M, 7, 7)`` **stencil**:
``stencil[i, j, 3 + di, 3 + dj] = (D^T D)[(i, j), (i + di, j + dj)]``, 49 numbers a row.

Assembly is one pass over the samples, accumulated per cell and then folded onto the
stencil; its memory is independent of the number of samples:

* B-spline (w = 1): ``B_a(t) B_a'(t)`` is a degree-6 polynomial in the local coordinate
  ``t``, so every 16 x 16 cell Gram block follows from the 49 per-cell moments
  ``sum_k Bern6_p(tx_k) Bern6_q(ty_k)`` (degree-6 Bernstein basis: all terms positive, no
  cancellation in float32). ``D^T b`` likewise from 16 cubic Bernstein moments.
* rational (fixed w): the 256 products of each row ``w_ij B_ij / W`` (eq. 23), accumulated
  in blocks of ``chunk_size`` samples (``lax.scan``) so that no ``(3m, 256)`` array exists.

The stencil is reusable: :func:`stencil_matvec` applies it in O(NM) (an I-PIA step in
normal-equation form costs nothing per sample), :func:`stencil_to_dense` builds the
``NM x NM`` matrix for a direct solve on small grids.
"""

from __future__ import annotations

import itertools
from math import comb
from typing import TYPE_CHECKING, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .._model.basis import (
    NUM_LOCAL,
    cell_shape,
    grid_to_patches,
    num_cells,
    patches_to_grid,
    tensor_basis,
)
from .._model.precision import full_precision
from .._model.spline import rational_terms
from .._problem.problem import Problem

if TYPE_CHECKING:  # SciPy loads when a stencil is converted, not on import
    import scipy.sparse
    from jax.typing import DTypeLike

#: Half-width of the stencil: cubic basis functions ``i`` and ``i + 3`` still share a cell.
HALF = 3
#: Stencil side, ``2 * HALF + 1``.
SIDE = 7
#: Default number of samples accumulated at once on the rational path (``chunk x 256``
#: floats: 32 MB in float64).
DEFAULT_CHUNK = 2**14


def _cubic_bernstein() -> np.ndarray:
    """Coefficients of the four uniform cubic B-spline pieces
    (:func:`jurs.internal.cubic_weights`) in the cubic Bernstein basis
    ``comb(3, p) t^p (1 - t)^(3 - p)``; ``(4, 4)``."""
    return np.array([[1, 0, 0, 0], [4, 4, 2, 1], [1, 2, 4, 4], [0, 0, 0, 1]], float) / 6.0


def _product_bernstein() -> np.ndarray:
    """``B_a(t) B_{a + d - 3}(t)`` in the degree-6 Bernstein basis; ``(4, 7, 7)`` indexed
    ``[a, d, p]``, zero where ``a + d - 3`` is not a piece. Products of Bernstein forms:
    ``Bern3_i Bern3_j = comb(3, i) comb(3, j) / comb(6, i + j) Bern6_{i + j}``."""
    cubic = _cubic_bernstein()
    out = np.zeros((4, SIDE, SIDE))
    for a in range(4):
        for d in range(SIDE):
            b = a + d - HALF
            if not 0 <= b < 4:
                continue
            for i in range(4):
                for j in range(4):
                    out[a, d, i + j] += (
                        cubic[a, i] * cubic[b, j] * comb(3, i) * comb(3, j) / comb(6, i + j)
                    )
    return out


def _bernstein(t: Array, degree: int) -> Array:
    """Bernstein basis of ``degree`` at ``t``; ``(..., degree + 1)``."""
    k = np.arange(degree + 1)
    binom = np.array([comb(degree, int(i)) for i in k], float)
    t = t[..., None]
    return jnp.asarray(binom, t.dtype) * t**k * (1.0 - t) ** (degree - k)


def _bernstein_terms(t: Array, degree: int) -> list:
    """The Bernstein basis of ``degree`` at ``t`` as a list of arrays shaped like ``t``,
    from products only (no ``pow``: inside a reduction every operand would evaluate it)."""
    s = 1.0 - t
    tp, sp = [jnp.ones_like(t)], [jnp.ones_like(t)]
    for _ in range(degree):
        tp.append(tp[-1] * t)
        sp.append(sp[-1] * s)
    return [comb(degree, p) * tp[p] * sp[degree - p] for p in range(degree + 1)]


def chunked_segment_sum(
    rows_fn,
    inputs,
    segments: Array,
    num_segments: int,
    chunk_size: int = DEFAULT_CHUNK,
    parts: int = 1,
) -> Array:
    """``segment_sum(rows_fn(*inputs), segments)`` computed ``chunk_size`` rows at a time.

    ``rows_fn`` maps a block of the ``inputs`` (arrays sharing a leading axis) to
    ``(block, ...)`` rows; it must return 0 rows for zero-padded inputs whose weight
    (the caller's mask) is 0. Peak memory is one block of rows, whatever the number of
    samples.

    ``parts``: the leading axis is taken as that many equal parts (the devices of a sharded
    fit, :attr:`jurs.LocalBasis.parts`), each summed a chunk at a time on its own, then
    the parts' sums added. Why: a scan over chunks of an axis split over devices walks
    across the devices, and the partitioner gathers every chunk to every device; chunks
    taken within each part stay where they are, and only the grid-sized sums are reduced.
    """
    n = segments.shape[0]
    parts = parts if parts > 1 and n % parts == 0 else 1
    per_part = n // parts
    if per_part <= chunk_size:
        return jax.ops.segment_sum(rows_fn(*inputs), segments, num_segments=num_segments)
    pad = (-per_part) % chunk_size
    blocks = (per_part + pad) // chunk_size

    def split(x):  # (n, ...) -> (blocks, parts, chunk, ...), each part padded on its own
        x = x.reshape((parts, per_part) + x.shape[1:])
        x = jnp.pad(x, [(0, 0), (0, pad)] + [(0, 0)] * (x.ndim - 2))
        return jnp.moveaxis(x.reshape((parts, blocks, chunk_size) + x.shape[2:]), 1, 0)

    split_inputs = [split(x) for x in inputs]
    split_segments = split(segments)
    out_struct = jax.eval_shape(rows_fn, *[x[0, 0] for x in split_inputs])

    def part_sum(seg, *xs):
        return jax.ops.segment_sum(rows_fn(*xs), seg, num_segments=num_segments)

    def body(total, block):
        return total + jax.vmap(part_sum)(*block), None

    total0 = jnp.zeros((parts, num_segments) + out_struct.shape[1:], out_struct.dtype)
    total, _ = jax.lax.scan(body, total0, [split_segments, *split_inputs])
    return total.sum(axis=0)


def _cells_to_stencil(blocks: Array, shape: tuple[int, ...]) -> Array:
    """Fold per-cell couplings onto the stencil.

    ``blocks`` is ``(cells, 16, 7, 7)``: for local term ``(a, b)`` of a cell, its coupling
    to the term at offset ``(da, db)`` (stored at ``[3 + da, 3 + db]``). Term ``(a, b)`` of
    cell ``(cx, cy)`` is coefficient ``(cx + a, cy + b)``, so this is the adjoint of the
    patch gather (:func:`jurs._model.basis.patches_to_grid`) with 49 channels.
    """
    n, m = shape[0] - 3, shape[1] - 3
    per_cell = blocks.reshape(n, m, NUM_LOCAL, SIDE, SIDE)
    stencil = jnp.zeros(shape + (SIDE, SIDE), blocks.dtype)
    for a in range(4):
        for b in range(4):
            stencil = stencil.at[a : a + n, b : b + m].add(per_cell[:, :, a * 4 + b])
    return stencil


def _gram_to_blocks(gram: Array) -> Array:
    """``(cells, 16, 16)`` Gram blocks -> ``(cells, 16, 7, 7)`` couplings by offset."""
    a = np.arange(4)[:, None, None, None]
    b = np.arange(4)[None, :, None, None]
    da = np.arange(SIDE)[None, None, :, None] - HALF
    db = np.arange(SIDE)[None, None, None, :] - HALF
    a2, b2 = a + da, b + db
    valid = (a2 >= 0) & (a2 < 4) & (b2 >= 0) & (b2 < 4)
    col = np.where(valid, a2 * 4 + b2, NUM_LOCAL)  # out of the cell -> a zero column
    col = np.broadcast_to(col, (4, 4, SIDE, SIDE)).reshape(NUM_LOCAL, SIDE * SIDE)
    padded = jnp.concatenate([gram, jnp.zeros(gram.shape[:2] + (1,), gram.dtype)], axis=-1)
    picked = jnp.take_along_axis(padded, jnp.asarray(col)[None], axis=-1)
    return picked.reshape(gram.shape[0], NUM_LOCAL, SIDE, SIDE)


def _local_coordinates(problem: Problem) -> Array:
    """``t (S, 2)`` of every sample in its cell (as stored in ``problem.local``)."""
    return problem.local.t.T


def _bernstein_moments(problem: Problem, chunk_size: int) -> Array:
    """Per-cell sums ``(cells, 7 ** d + 4 ** d)``: ``sum_k mask Bern6_p(tx) Bern6_q(ty)`` and
    ``sum_k b_k Bern3_p(tx) Bern3_q(ty)`` over the samples of each cell (with a third
    factor per term in 3D)."""
    local = problem.local
    count = num_cells(problem.shape)
    if local.bucket_size > 1:
        # Bucketed layout: the 65 sums of each bucket are one variadic reduction over its
        # slots (no (samples x 65) array, no scatter), then a sorted sum per cell.
        k = local.bucket_size
        t = local.t.reshape(2, -1, k)
        mask = problem.mask.reshape(-1, k)
        target = (problem.mask * problem.targets).reshape(-1, k)
        b6x, b6y = _bernstein_terms(t[0], 6), _bernstein_terms(t[1], 6)
        b3x, b3y = _bernstein_terms(t[0], 3), _bernstein_terms(t[1], 3)
        terms = [mask * b6x[p] * b6y[q] for p in range(7) for q in range(7)]
        terms += [target * b3x[p] * b3y[q] for p in range(4) for q in range(4)]
        zeros = tuple(jnp.zeros((), t.dtype) for _ in terms)
        sums = jax.lax.reduce(
            tuple(terms), zeros, lambda a, b: tuple(x + y for x, y in zip(a, b)), (1,)
        )
        return jax.ops.segment_sum(
            jnp.stack(sums, axis=-1), local.bucket_cell, num_segments=count, indices_are_sorted=True
        )
    t = _local_coordinates(problem)

    def moments(t, mask, target):
        axes = range(t.shape[1])
        gram = tensor_basis(*[_bernstein(t[:, a], 6) for a in axes])
        rhs = tensor_basis(*[_bernstein(t[:, a], 3) for a in axes]) * target[:, None]
        return jnp.concatenate([gram, rhs], axis=1) * mask[:, None]

    inputs = [t, problem.mask, problem.targets]
    return chunked_segment_sum(moments, inputs, local.cell, count, chunk_size, local.parts)


def _fold_axis(cells: Array, kernel: Array, axis: int) -> Array:
    """One axis of the moment-to-stencil fold: ``out[i] = sum_a kernel[a] . cells[i - a]``
    along ``axis`` (cells outside the range are 0), contracting the cell array's channel
    axis ``-1`` (moment degree) with ``kernel[a]``'s last axis and putting the offset
    channel (``kernel``'s middle axis) in its place. ``cells`` has ``n - 3`` entries along
    ``axis``, the result ``n``."""
    out = 0.0
    for a in range(4):
        part = jnp.tensordot(cells, kernel[a], axes=[[-1], [1]])  # (..., offset)
        pad = [(0, 0)] * part.ndim
        pad[axis] = (a, 3 - a)
        out = out + jnp.pad(part, pad)
    return cast(Array, out)  # the loop runs: never the float 0.0


def _fold_axes(cells: Array, kernel: Array) -> Array:
    """The moment-to-stencil fold over every axis: ``cells`` is ``cell_grid + (channels,) *
    d`` (channel axis ``d + a`` the moment degree along axis ``a``), the result
    ``grid + (7,) * d`` (or ``(1,) * d`` for the right-hand side's kernel). One axis at a
    time: its degree channel moved last, folded, its offset channel put back."""
    d = (cells.ndim) // 2
    for axis in range(d):
        folded = _fold_axis(jnp.moveaxis(cells, d + axis, -1), kernel, axis)
        cells = jnp.moveaxis(folded, -1, d + axis)
    return cells


def bspline_normal_equations(problem: Problem, chunk_size: int = DEFAULT_CHUNK):
    """``(stencil, D^T b)`` for the B-spline collocation (w = 1) from per-cell Bernstein
    moments: 7 ** d + 4 ** d channels a sample (49 + 16 in 2D), never the ``16 ** d``
    products. Any grid dimension d.

    Coefficient ``(i, j)`` couples to ``(i + da - 3, j + db - 3)`` through every cell
    ``(i - a, j - b)`` both touch, with ``sum_pq P[a, da, p] P[b, db, q] moment[p, q]``;
    that sum factorises by axis, so the fold runs as one pass over the grid an axis
    with 7 channels each, never a ``(cells, 16, 7, 7)`` array (which dominated the
    assembly: 45 of 47 ms at 3000 samples on a 92 x 96 grid)."""
    dtype = problem.local.s.dtype
    ndim = problem.ndim
    sums = _bernstein_moments(problem, chunk_size)
    cells = cell_shape(problem.shape)
    gram_moments = sums[:, : 7**ndim].reshape(cells + (7,) * ndim)  # [cells..., p, q(, r)]
    rhs_moments = sums[:, 7**ndim :].reshape(cells + (4,) * ndim)
    stencil = _fold_axes(gram_moments, jnp.asarray(_product_bernstein(), dtype))  # [a, da, p]
    cubic = jnp.asarray(_cubic_bernstein(), dtype)[:, None, :]  # [a, 1, p]: B_a in Bern3
    rhs = _fold_axes(rhs_moments, cubic)
    return stencil, rhs.reshape(problem.shape)


def rational_normal_equations(problem: Problem, weights: Array, chunk_size: int = DEFAULT_CHUNK):
    """``(stencil, D^T b)`` for the rational collocation rows ``w_ij B_ij / W`` (eq. 23) of
    fixed ``weights``: the 16 x 16 products of each row, accumulated ``chunk_size`` samples
    at a time. 2D only (NotImplementedError for a surface: its 64 x 64 row products are not
    written yet)."""
    if problem.ndim != 2:
        raise NotImplementedError(
            "the rational normal equations (fixed weights other than "
            "1) are 2D only; fit surfaces with the B-spline "
            "(LeastSquares(keep_weights=False), the default)"
        )
    w_patches = jnp.take(grid_to_patches(weights), problem.local.cell, axis=0)

    def products(bx, by, w_rows, mask, target):
        basis = (bx[:, :, None] * by[:, None, :]).reshape(-1, NUM_LOCAL)
        wb = basis * w_rows
        denom = jnp.sum(wb, axis=1)
        # Zero-padded blocks have W = 0: divide by 1 there (their mask is 0 anyway).
        rows = wb * (mask / jnp.where(denom > 0, denom, 1.0))[:, None]
        gram = (rows[:, :, None] * rows[:, None, :]).reshape(-1, NUM_LOCAL * NUM_LOCAL)
        return jnp.concatenate([gram, rows * target[:, None]], axis=1)

    inputs = [problem.local.bx, problem.local.by, w_patches, problem.mask, problem.targets]
    cells = num_cells(problem.shape)
    sums = chunked_segment_sum(
        products, inputs, problem.local.cell, cells, chunk_size, problem.local.parts
    )
    gram = sums[:, : NUM_LOCAL * NUM_LOCAL].reshape(-1, NUM_LOCAL, NUM_LOCAL)
    stencil = _cells_to_stencil(_gram_to_blocks(gram), problem.shape)
    return stencil, patches_to_grid(sums[:, NUM_LOCAL * NUM_LOCAL :], problem.shape)


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
    """The grid Laplacian L of :func:`jurs.internal.grid_laplacian` (free boundary) as a
    stencil, for a grid of any dimension d: degree at the centre, -1 towards each existing
    one of the ``2 d`` axis neighbours."""
    d = len(shape)
    stencil = jnp.zeros(tuple(shape) + (SIDE,) * d, dtype)
    centre = (HALF,) * d
    degree = jnp.zeros(shape, dtype)
    for axis, n in enumerate(shape):
        index = jnp.arange(n).reshape((n,) + (1,) * (d - 1 - axis))
        for step, exists in ((-1, index > 0), (1, index < n - 1)):
            exists = jnp.broadcast_to(exists, shape).astype(dtype)
            offset: list[int] = list(centre)
            offset[axis] += step
            stencil = stencil.at[(Ellipsis, *offset)].set(-exists)
            degree = degree + exists
    return stencil.at[(Ellipsis, *centre)].set(degree)


def stencil_matvec(stencil: Array, grid: Array) -> Array:
    """Apply a ``grid_shape + (7,) * d`` stencil to a ``grid_shape`` grid (zero outside the
    grid), for any grid dimension d (49 terms in 2D, 343 in 3D)."""
    d = grid.ndim
    padded = jnp.pad(grid, HALF)
    out = jnp.zeros_like(grid)
    for offset in _offsets(d):
        window = tuple(slice(o, o + n) for o, n in zip(offset, grid.shape))
        out = out + stencil[(Ellipsis, *offset)] * padded[window]
    return out


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


#: Largest diagonal block that :func:`_cholesky_and_inverse` hands to LAPACK. Above about
#: 1000 entries OpenBLAS runs these kernels threaded, and next to XLA's own threads that was
#: measured at 10-700 ms a call instead of 0.01-2 ms on a 2-core machine; the larger blocks
#: are split recursively into matrix products, which XLA runs itself.
_LAPACK_MAX_BLOCK = 16


def _cholesky_and_inverse(a: Array):
    """``(L, L^-1)`` of a symmetric positive definite matrix ``a = L L^T``, recursively:
    ``L = [[L1, 0], [B, L2]]`` with ``L1 = chol(A11)``, ``B = A21 L1^-T`` and
    ``L2 = chol(A22 - B B^T)``."""
    n = a.shape[0]
    if n <= _LAPACK_MAX_BLOCK:
        low = jax.lax.linalg.cholesky(a, symmetrize_input=False)
        inv = jax.lax.linalg.triangular_solve(
            low, jnp.eye(n, dtype=a.dtype), left_side=True, lower=True
        )
        return low, inv
    h = n // 2
    l1, i1 = _cholesky_and_inverse(a[:h, :h])
    b = a[h:, :h] @ i1.T
    l2, i2 = _cholesky_and_inverse(a[h:, h:] - b @ b.T)
    zero = jnp.zeros((h, n - h), a.dtype)
    low = jnp.block([[l1, zero], [b, l2]])
    inv = jnp.block([[i1, zero], [-(i2 @ b) @ i1, i2]])
    return low, inv


def _row_blocks(stencil_row: Array, row: Array) -> tuple:
    """The blocks ``A[row i, row i - d]``, ``d = 0..3``, of a stencil's matrix from grid row
    ``i``'s stencil ``(M, 7, 7)``; zero where ``i - d < 0``. Rows further apart do not couple
    (``|di| <= 3``), so these and their transposes are all of A."""
    m = stencil_row.shape[0]
    out = []
    for d in range(HALF + 1):
        band = stencil_row[:, HALF - d, :]  # (M, 7): A[(i, j), (i - d, j + dj)] at 3 + dj
        # Shear: rows of length M + 7 read back with length M + 6 shift row j right by j,
        # putting band[j, c] at column j + c, i.e. at j + dj + 3.
        sheared = jnp.pad(band, ((0, 0), (0, m))).reshape(m * (m + SIDE))
        block = sheared[: m * (m + SIDE - 1)].reshape(m, m + SIDE - 1)[:, HALF : HALF + m]
        out.append(jnp.where(row >= d, block, 0.0))
    return tuple(out)


#: Largest ``N * min(N, M)^2`` for which LeastSquares solves directly by
#: :func:`stencil_cholesky_solve` (its factor takes ``32 N M^2`` bytes in float64: 1 GB at
#: 256 x 256); above, CG.
DIRECT_MAX_ENTRIES = 1 << 25


@full_precision
def stencil_cholesky_solve(stencil: Array, rhs: Array) -> Array:
    """Solve ``stencil * C = rhs`` for a symmetric positive definite stencil by a block
    Cholesky factorisation ``A = L L^T`` in blocks of grid lines.

    Grid lines couple only to lines at most 3 apart, so L is block-banded with 3 blocks below
    the diagonal; one pass over the lines (a scan) computes them and the inverse of each
    diagonal block, then two passes solve with L and L^T. Blocks run along the longer axis,
    so they are as small as possible. Work ``O(N M^3)``, memory ``O(N M^2)`` (``M`` the
    shorter side): on a 128 x 128 grid about 2.6e9 multiply-adds as 128 x 128 matrix
    products, against tens of thousands of Jacobi-CG steps for the ill-conditioned systems
    of sparse data with a small lambda. A direct solve: no tolerance, residual at rounding
    level. Non-finite output means the matrix was not numerically positive definite.
    """
    if rhs.shape[1] > rhs.shape[0]:  # blocks along the shorter side
        swapped = jnp.transpose(stencil, (1, 0, 3, 2))
        return stencil_cholesky_solve(swapped, rhs.T).T
    n, m = rhs.shape
    dtype = rhs.dtype

    def factor(carry, x):
        # prev[r, c] = L[i-1-r, i-1-r-(3-c)], inv[r] = L[i-1-r, i-1-r]^-1, r = 0..2.
        prev, inv = carry
        a0, a1, a2, a3 = _row_blocks(*x)  # A[i, i - d]
        l3 = a3 @ inv[2].T
        l2 = (a2 - l3 @ prev[1, 2].T) @ inv[1].T
        l1 = (
            a1 - jnp.concatenate([l3, l2], 1) @ jnp.concatenate([prev[0, 1], prev[0, 2]], 1).T
        ) @ inv[0].T
        row = jnp.stack([l3, l2, l1])
        wide = jnp.concatenate([l3, l2, l1], 1)
        _, inv_d = _cholesky_and_inverse(a0 - wide @ wide.T)
        return (jnp.stack([row, prev[0], prev[1]]), jnp.stack([inv_d, inv[0], inv[1]])), (
            row,
            inv_d,
        )

    eye = jnp.broadcast_to(jnp.eye(m, dtype=dtype), (3, m, m))
    carry = (jnp.zeros((3, 3, m, m), dtype), eye)
    _, (rows, invs) = jax.lax.scan(factor, carry, (stencil, jnp.arange(n)))

    def forward(ys, x):  # y_i = L_ii^-1 (b_i - sum_d L[i, i-d] y_{i-d})
        row, inv, b = x
        y = inv @ (b - row[0] @ ys[2] - row[1] @ ys[1] - row[2] @ ys[0])
        return jnp.stack([y, ys[0], ys[1]]), y

    zeros = jnp.zeros((3, m), dtype)
    _, y = jax.lax.scan(forward, zeros, (rows, invs, rhs))

    def backward(pending, x):
        # x_i = L_ii^-T (y_i - sum_d L[i+d, i]^T x_{i+d}); the sums arrive in ``pending``
        # from the lines already solved, and x_i adds its share to the three lines above.
        row, inv, yi = x
        xi = inv.T @ (yi - pending[0])
        return jnp.stack(
            [pending[1] + row[2].T @ xi, pending[2] + row[1].T @ xi, row[0].T @ xi]
        ), xi

    _, x = jax.lax.scan(backward, zeros, (rows, invs, y), reverse=True)
    return x


def stencil_to_scipy(stencil) -> scipy.sparse.csr_matrix:
    """The stencil as a SciPy CSR matrix (NumPy side, for inspection or SciPy solvers)."""
    import scipy.sparse as sp

    s = np.asarray(stencil)
    shape = s.shape[: stencil_ndim(s)]
    row, col, valid = _stencil_indices(shape)
    keep = valid & (s != 0)
    size = int(np.prod(shape))
    return sp.csr_matrix((s[keep], (row[keep], col[keep])), shape=(size, size))


class NormalEquations(eqx.Module):
    """``D^T D`` as an ``(N, M, 7, 7)`` stencil and ``D^T b`` as an ``(N, M)`` grid.

    Build with :func:`normal_equations`. ``matvec`` applies ``D^T D``; ``E_d(C)`` equals
    ``C.(D^T D) C - 2 C.(D^T b) + b.b`` (``b.b`` in ``target_norm2``).
    """

    stencil: Array
    rhs: Array
    target_norm2: Array

    def matvec(self, control: Array) -> Array:
        return stencil_matvec(self.stencil, control)

    def data_energy(self, control: Array, product: Array | None = None) -> Array:
        """E_d (eq. 16) from the normal equations, O(NM) whatever the number of samples;
        ``product``, ``matvec(control)``, where the caller has it already."""
        product = self.matvec(control) if product is None else product
        return jnp.vdot(control, product - 2.0 * self.rhs) + self.target_norm2

    def regularised(self, lam) -> Array:
        """The stencil of ``D^T D + 2 lam L``, the Hessian / 2 of ``E_d + lam R``
        (docs/design.md section 3)."""
        lap = laplacian_stencil(self.rhs.shape, self.stencil.dtype)
        return self.stencil + 2.0 * lam * lap

    def to_dense(self) -> Array:
        return stencil_to_dense(self.stencil)


@full_precision
def normal_equations(
    problem: Problem, weights: Array | None = None, *, chunk_size: int = DEFAULT_CHUNK
) -> NormalEquations:
    """Assemble ``D^T D`` (stencil) and ``D^T b`` for ``problem`` in one pass over the samples.

    ``weights=None`` is the B-spline (w = 1, eq. 6), assembled from per-cell Bernstein
    moments; otherwise the rational rows of eq. 23 with those fixed ``(N, M)`` weights.
    Masked-out samples (padding) contribute nothing. Differentiable in the points,
    normals, targets and weights.
    """
    if weights is None:
        stencil, rhs = bspline_normal_equations(problem, chunk_size)
    else:
        stencil, rhs = rational_normal_equations(problem, weights, chunk_size)
    b = problem.mask * problem.targets
    return NormalEquations(stencil=stencil, rhs=rhs, target_norm2=jnp.sum(b * b))


def collocation_rows(problem: Problem, weights: Array) -> Array:
    """The 16 non-zeros of every row of D (eq. 23), masked; ``(3m, 16)``. For tests and
    small problems (it is 16 floats a sample)."""
    wb, denom, _ = rational_terms(problem.local, jnp.zeros_like(weights), weights)
    return wb * (problem.mask / denom)[:, None]
