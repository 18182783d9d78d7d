"""The normal equations of the collocation least-squares problem, without forming D.

For fixed weights the data energy ``E_d = ||D C - b||^2`` is quadratic in C, and its
minimiser (with the regulariser of eq. 31) solves ``(D^T D + 2 lam L) C = D^T b``
(DESIGN 3). ``D^T D`` is banded: coefficient ``(i, j)`` couples only to ``(i + di, j + dj)``
with ``|di|, |dj| <= 3`` (two cubic basis functions overlap when their supports share a
cell), so it is stored as an ``(N, M, 7, 7)`` **stencil**:
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

from math import comb

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from ._basis import NUM_LOCAL, grid_to_patches, locate, num_cells, patches_to_grid
from ._problem import Problem
from ._spline import rational_terms

#: Half-width of the stencil: cubic basis functions ``i`` and ``i + 3`` still share a cell.
HALF = 3
#: Stencil side, ``2 * HALF + 1``.
SIDE = 7
#: Default number of samples accumulated at once on the rational path (``chunk x 256``
#: floats: 32 MB in float64).
DEFAULT_CHUNK = 2**14


def _cubic_bernstein() -> np.ndarray:
    """Coefficients of the four uniform cubic B-spline pieces (:func:`jurs.cubic_weights`)
    in the cubic Bernstein basis ``comb(3, p) t^p (1 - t)^(3 - p)``; ``(4, 4)``."""
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
                    out[a, d, i + j] += cubic[a, i] * cubic[b, j] * comb(3, i) * comb(3, j) / comb(6, i + j)
    return out


def _bernstein(t: Array, degree: int) -> Array:
    """Bernstein basis of ``degree`` at ``t``; ``(..., degree + 1)``."""
    k = np.arange(degree + 1)
    binom = np.array([comb(degree, int(i)) for i in k], float)
    t = t[..., None]
    return jnp.asarray(binom, t.dtype) * t**k * (1.0 - t) ** (degree - k)


def chunked_segment_sum(rows_fn, inputs, segments: Array, num_segments: int,
                        chunk_size: int = DEFAULT_CHUNK) -> Array:
    """``segment_sum(rows_fn(*inputs), segments)`` computed ``chunk_size`` rows at a time.

    ``rows_fn`` maps a block of the ``inputs`` (arrays sharing a leading axis) to
    ``(block, ...)`` rows; it must return 0 rows for zero-padded inputs whose weight
    (the caller's mask) is 0. Peak memory is one block of rows, whatever the number of
    samples.
    """
    n = segments.shape[0]
    if n <= chunk_size:
        return jax.ops.segment_sum(rows_fn(*inputs), segments, num_segments=num_segments)
    pad = (-n) % chunk_size
    blocks = (n + pad) // chunk_size

    def split(x):
        x = jnp.pad(x, [(0, pad)] + [(0, 0)] * (x.ndim - 1))
        return x.reshape((blocks, chunk_size) + x.shape[1:])

    split_inputs = [split(x) for x in inputs]
    split_segments = split(segments)
    out_struct = jax.eval_shape(rows_fn, *[x[0] for x in split_inputs])

    def body(total, block):
        seg, *xs = block
        return total + jax.ops.segment_sum(rows_fn(*xs), seg, num_segments=num_segments), None

    total0 = jnp.zeros((num_segments,) + out_struct.shape[1:], out_struct.dtype)
    total, _ = jax.lax.scan(body, total0, [split_segments, *split_inputs])
    return total


def _cells_to_stencil(blocks: Array, shape: tuple[int, int]) -> Array:
    """Fold per-cell couplings onto the stencil.

    ``blocks`` is ``(cells, 16, 7, 7)``: for local term ``(a, b)`` of a cell, its coupling
    to the term at offset ``(da, db)`` (stored at ``[3 + da, 3 + db]``). Term ``(a, b)`` of
    cell ``(cx, cy)`` is coefficient ``(cx + a, cy + b)``, so this is the adjoint of the
    patch gather (:func:`jurs._basis.patches_to_grid`) with 49 channels.
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
    """``t`` of every sample in its cell (the same :func:`jurs._basis.locate` that built
    ``problem.local``, so cells agree)."""
    _, t = locate(problem.samples, problem.lower, problem.upper, problem.shape)
    return t


def bspline_normal_equations(problem: Problem, chunk_size: int = DEFAULT_CHUNK):
    """``(stencil, D^T b)`` for the B-spline collocation (w = 1) from per-cell Bernstein
    moments: 49 + 16 channels a sample, never the 256 products."""
    t = _local_coordinates(problem)
    dtype = t.dtype

    def moments(t, mask, target):
        b6x, b6y = _bernstein(t[:, 0], 6), _bernstein(t[:, 1], 6)
        b3x, b3y = _bernstein(t[:, 0], 3), _bernstein(t[:, 1], 3)
        gram = (b6x[:, :, None] * b6y[:, None, :]).reshape(-1, 49)
        rhs = (b3x[:, :, None] * b3y[:, None, :]).reshape(-1, 16) * target[:, None]
        return jnp.concatenate([gram, rhs], axis=1) * mask[:, None]

    sums = chunked_segment_sum(moments, [t, problem.mask, problem.targets], problem.local.cell,
                               num_cells(problem.shape), chunk_size)
    gram_moments = sums[:, :49].reshape(-1, 7, 7)
    rhs_moments = sums[:, 49:].reshape(-1, 4, 4)
    products = jnp.asarray(_product_bernstein(), dtype)  # [a, da, p]
    # Coupling of local term (a, b) to (a + da - 3, b + db - 3), summed over the cell:
    # sum_pq P[a, da, p] P[b, db, q] moment[p, q].
    blocks = jnp.einsum("adp,beq,cpq->cabde", products, products, gram_moments, optimize=True)
    stencil = _cells_to_stencil(blocks.reshape(-1, NUM_LOCAL, SIDE, SIDE), problem.shape)
    cubic = jnp.asarray(_cubic_bernstein(), dtype)  # [a, p]
    rhs_patches = jnp.einsum("ap,bq,cpq->cab", cubic, cubic, rhs_moments).reshape(-1, NUM_LOCAL)
    return stencil, patches_to_grid(rhs_patches, problem.shape)


def rational_normal_equations(problem: Problem, weights: Array, chunk_size: int = DEFAULT_CHUNK):
    """``(stencil, D^T b)`` for the rational collocation rows ``w_ij B_ij / W`` (eq. 23) of
    fixed ``weights``: the 16 x 16 products of each row, accumulated ``chunk_size`` samples
    at a time."""
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
    sums = chunked_segment_sum(products, inputs, problem.local.cell, num_cells(problem.shape),
                               chunk_size)
    gram = sums[:, : NUM_LOCAL * NUM_LOCAL].reshape(-1, NUM_LOCAL, NUM_LOCAL)
    stencil = _cells_to_stencil(_gram_to_blocks(gram), problem.shape)
    return stencil, patches_to_grid(sums[:, NUM_LOCAL * NUM_LOCAL :], problem.shape)


def laplacian_stencil(shape: tuple[int, int], dtype=float) -> Array:
    """The grid Laplacian L of :func:`jurs.grid_laplacian` (free boundary) as a stencil:
    degree at the centre, -1 towards each existing 4-neighbour."""
    n, m = shape
    i = jnp.arange(n)[:, None]
    j = jnp.arange(m)[None, :]
    left, right = (i > 0).astype(dtype), (i < n - 1).astype(dtype)
    down, up = (j > 0).astype(dtype), (j < m - 1).astype(dtype)
    left, right = jnp.broadcast_to(left, shape), jnp.broadcast_to(right, shape)
    down, up = jnp.broadcast_to(down, shape), jnp.broadcast_to(up, shape)
    stencil = jnp.zeros(shape + (SIDE, SIDE), dtype)
    stencil = stencil.at[:, :, HALF, HALF].set(left + right + down + up)
    stencil = stencil.at[:, :, HALF - 1, HALF].set(-left)
    stencil = stencil.at[:, :, HALF + 1, HALF].set(-right)
    stencil = stencil.at[:, :, HALF, HALF - 1].set(-down)
    return stencil.at[:, :, HALF, HALF + 1].set(-up)


def stencil_matvec(stencil: Array, grid: Array) -> Array:
    """Apply a ``(N, M, 7, 7)`` stencil to an ``(N, M)`` grid (zero outside the grid)."""
    n, m = grid.shape
    padded = jnp.pad(grid, HALF)
    out = jnp.zeros_like(grid)
    for da in range(SIDE):
        for db in range(SIDE):
            out = out + stencil[:, :, da, db] * padded[da : da + n, db : db + m]
    return out


def stencil_diagonal(stencil: Array) -> Array:
    """The diagonal of the matrix a stencil stands for, as an ``(N, M)`` grid."""
    return stencil[:, :, HALF, HALF]


def stencil_to_dense(stencil: Array) -> Array:
    """The ``NM x NM`` matrix of a stencil (row-major flattening of the grid), for direct
    solves on small grids: ``NM^2`` entries, 49 of them non-zero per row."""
    n, m = stencil.shape[:2]
    i = jnp.arange(n)[:, None, None, None]
    j = jnp.arange(m)[None, :, None, None]
    di = jnp.arange(SIDE)[None, None, :, None] - HALF
    dj = jnp.arange(SIDE)[None, None, None, :] - HALF
    i2, j2 = i + di, j + dj
    valid = (i2 >= 0) & (i2 < n) & (j2 >= 0) & (j2 < m)
    row = jnp.broadcast_to(i * m + j, stencil.shape)
    # Out-of-grid entries are 0 in the stencil; send them to column 0 with value 0.
    col = jnp.where(valid, i2 * m + j2, 0)
    values = jnp.where(valid, stencil, 0.0)
    return jnp.zeros((n * m, n * m), stencil.dtype).at[row.ravel(), col.ravel()].add(values.ravel())


def stencil_to_scipy(stencil) -> "scipy.sparse.csr_matrix":  # noqa: F821
    """The stencil as a SciPy CSR matrix (NumPy side, for inspection or SciPy solvers)."""
    import scipy.sparse as sp

    s = np.asarray(stencil)
    n, m = s.shape[:2]
    i, j, di, dj = np.meshgrid(np.arange(n), np.arange(m), np.arange(SIDE) - HALF,
                               np.arange(SIDE) - HALF, indexing="ij")
    i2, j2 = i + di, j + dj
    keep = (i2 >= 0) & (i2 < n) & (j2 >= 0) & (j2 < m) & (s != 0)
    return sp.csr_matrix(((s[keep]), ((i * m + j)[keep], (i2 * m + j2)[keep])), shape=(n * m, n * m))


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

    def data_energy(self, control: Array) -> Array:
        """E_d (eq. 16) from the normal equations, O(NM) whatever the number of samples."""
        return (jnp.vdot(control, self.matvec(control) - 2.0 * self.rhs) + self.target_norm2)

    def regularised(self, lam) -> Array:
        """The stencil of ``D^T D + 2 lam L``, the Hessian / 2 of ``E_d + lam R`` (DESIGN 3)."""
        lap = laplacian_stencil(self.rhs.shape, self.stencil.dtype)
        return self.stencil + 2.0 * lam * lap

    def to_dense(self) -> Array:
        return stencil_to_dense(self.stencil)


def normal_equations(problem: Problem, weights: Array | None = None, *,
                     chunk_size: int = DEFAULT_CHUNK) -> NormalEquations:
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
