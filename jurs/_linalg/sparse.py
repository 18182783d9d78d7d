"""Sparse matrices assembled on the host (SciPy): applied in JAX as COO entries padded
to a size class, so that one compiled program serves every matrix whose sizes fall in it;
applied on the host by SciPy, their rows split in blocks whose products run in threads.

Padded entries are zeros at (0, 0), which add exactly nothing to a product, and padded
rows and columns hold no entry, so a padded vector's extra entries stay 0. The products
are gathers and segment sums, the same on any device. Used by the hierarchy's CG solves
(``jurs._fit.adaptive``) and by the device V-cycle (``jurs._linalg.thb_multigrid``)."""

from __future__ import annotations

from contextlib import contextmanager

import equinox as eqx
import jax
import numpy as np
from jax import Array

from .._problem.sizes import padded_to
from .._threads import host_threads, pool, row_blocks


def padded_entries(matrix, count: int, dtype) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(rows, cols, values)`` of a SciPy sparse ``matrix`` on the host, padded to ``count``
    entries with zeros at (0, 0); indices int32, values in ``dtype``."""
    coo = matrix.tocoo()
    return (
        padded_to(coo.row.astype(np.int32), count),
        padded_to(coo.col.astype(np.int32), count),
        padded_to(coo.data.astype(dtype), count),
    )


class PaddedCoo(eqx.Module):
    """A sparse matrix as padded COO entries on JAX's device (``padded_entries``), its
    padded shape static: ``A @ x`` and ``A.transpose_apply(y)`` (``A^T y``)."""

    rows: Array
    cols: Array
    values: Array
    num_rows: int = eqx.field(static=True)
    num_cols: int = eqx.field(static=True)

    @classmethod
    def from_scipy(cls, matrix, count: int, shape: tuple[int, int], dtype) -> PaddedCoo:
        """``matrix`` (SciPy) padded to ``count`` entries and to the ``shape`` its vectors
        are padded to, in ``dtype`` (``jax.device_put`` of host arrays: nothing
        compiled for a new size)."""
        rows, cols, values = padded_entries(matrix, count, dtype)
        put = jax.device_put
        return cls(put(rows), put(cols), put(values), int(shape[0]), int(shape[1]))

    def __matmul__(self, x: Array) -> Array:
        return jax.ops.segment_sum(self.values * x[self.cols], self.rows, self.num_rows)

    def transpose_apply(self, y: Array) -> Array:
        return jax.ops.segment_sum(self.values * y[self.rows], self.cols, self.num_cols)


#: ``gram`` multiplies ``D``'s rows in blocks of at least this many entries, and at most
#: ``GRAM_BLOCKS`` of them: below, sorting the rows and summing the parts costs more than
#: the split saves.
MIN_GRAM_ENTRIES = 1 << 20
GRAM_BLOCKS = 8


def _weighted_rows(rows, weights):
    """A CSR block with each row scaled by its weight (a copy; the block itself when None)."""
    if weights is None:
        return rows
    scaled = rows.copy()
    scaled.data *= np.repeat(weights, np.diff(rows.indptr))
    return scaled


def rows_in_order(matrix) -> np.ndarray:
    """The order in which the products with a hierarchy's collocation matrix take its
    rows: by each row's largest column index (an empty row first), ties in their own
    order, for a SciPy CSR ``matrix``. A hierarchy's functions are numbered level by level
    and, on a level, along its grid, and a sample's last column is a function of its own
    leaf: in this order consecutive rows read neighbouring functions, where the samples
    themselves come in the cloud's order, which may be any."""
    last = np.full(matrix.shape[0], -1, np.int64)
    filled = np.diff(matrix.indptr) > 0
    if filled.any():
        last[filled] = np.maximum.reduceat(matrix.indices, matrix.indptr[:-1][filled])
    return np.argsort(last, kind="stable")


def ordered_rows(collocation) -> tuple:
    """``(D, order)``: a copy of the SciPy CSR ``collocation`` with its rows in
    ``rows_in_order``'s order, and that order (the samples' targets and row weights are
    taken through it alike). A solve keeps it for all its products with ``D``: in the
    samples' own order ``D c`` would gather and ``D^T y`` scatter all over ``c``
    (docs/performance.md, "The hierarchy's CG by rows in order")."""
    order = rows_in_order(collocation)
    return collocation[order], order


def gram(collocation, row_weights=None, threads=None):
    """``D^T S D`` (SciPy CSR) of a SciPy CSR ``collocation`` ``D``, ``S`` the rows'
    ``row_weights`` (None: 1): the data term of the assembled normal equations.

    The rows are taken in ``rows_in_order``'s order and cut in up to ``GRAM_BLOCKS``
    blocks (one per ``MIN_GRAM_ENTRIES`` entries), so each block holds the samples of one
    slab of the band: its product ``D_k^T S_k D_k`` touches about its share of the
    functions. The blocks run in ``threads`` threads (None: ``host_threads``; SciPy's
    sparse products release the GIL) and their products are summed pairwise in a fixed
    order, so the result has the same bits whatever the threads. Beside one product of
    all rows this is faster (each product works within a slab) and needs less memory at
    once (a block's copy and its product, not all rows' products over all functions).
    """
    threads = host_threads() if threads is None else max(1, int(threads))
    count = max(1, min(GRAM_BLOCKS, collocation.nnz // MIN_GRAM_ENTRIES))
    weights = None if row_weights is None else np.asarray(row_weights, float)
    if count == 1:
        return (collocation.T.tocsr() @ _weighted_rows(collocation, weights)).tocsr()
    order = rows_in_order(collocation)

    def part(rows):
        block = collocation[rows]
        return block.T.tocsr() @ _weighted_rows(block, None if weights is None else weights[rows])

    parts = list(pool("map", min(threads, count)).map(part, np.array_split(order, count)))
    while len(parts) > 1:
        pairs = range(0, len(parts) - 1, 2)
        parts = [parts[i] + parts[i + 1] for i in pairs] + parts[len(parts) - len(parts) % 2 :]
    return parts[0].tocsr()


def normal_system(matrices, targets, lam: float, row_weights=None):
    """``(D^T S D + lam R, D^T S b)`` on the host (SciPy CSR, float64): the assembled
    normal equations that a factorisation, a multilevel solve or CG on the assembled
    matrix reads. ``matrices``: ``(D, R)`` in SciPy CSR, ``R`` the regulariser's part of
    the normal matrix per unit lambda; ``b`` the samples' ``targets``, ``S`` their
    ``row_weights`` (None: 1). ``D^T S D`` comes from ``gram``."""
    collocation, regulariser = matrices
    weights = None if row_weights is None else np.asarray(row_weights, float)
    data = gram(collocation, weights)
    b = np.asarray(targets, float)
    rhs = collocation.T @ (b if weights is None else weights * b)
    return (data + lam * regulariser).tocsr(), rhs


@contextmanager
def normal_product(collocation, regulariser, lam: float, row_weights=None, threads=None):
    """``c -> D^T S D c + lam R c`` on the host (float64), for a context: ``D``
    (``collocation``) and ``R`` (``regulariser``) SciPy CSR matrices, ``S`` the rows'
    ``row_weights`` (None: 1). Their rows are split in ``threads`` blocks (``row_blocks``;
    None: ``host_threads``), each block's products in a thread of its own: SciPy's sparse
    products release the GIL, so the blocks run side by side. ``D^T`` is applied as the
    product of ``D``'s transpose view (CSC), with no transposed copy of ``D``. A
    hierarchy's solves pass ``D`` as ``ordered_rows`` gives it (the weights in its order),
    so that each thread's block covers a slab of the band. With
    ``collocation`` None, ``c -> lam R c``: the product of an assembled normal matrix
    (``normal_system``) with ``lam = 1``."""
    threads = host_threads() if threads is None else max(1, int(threads))
    weights = None if row_weights is None else np.asarray(row_weights, float)
    data = [] if collocation is None else row_blocks(collocation, threads)
    smooth = row_blocks(regulariser, threads)
    n = regulariser.shape[0]

    def block(k, c):
        out = np.zeros(n)
        if k < len(data):
            first, rows = data[k]
            y = rows @ c
            if weights is not None:
                y *= weights[first : first + rows.shape[0]]
            out += rows.T @ y
        if k < len(smooth):
            first, rows = smooth[k]
            out[first : first + rows.shape[0]] += lam * (rows @ c)
        return out

    count = max(len(data), len(smooth))
    if count <= 1:
        yield lambda c: block(0, np.asarray(c, float))
        return
    workers = pool("map", count)

    def apply(c) -> np.ndarray:
        c = np.asarray(c, float)
        first, *rest = workers.map(lambda k: block(k, c), range(count))
        for part in rest:
            first += part
        return first

    yield apply
