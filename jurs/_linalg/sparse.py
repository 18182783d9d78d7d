"""Sparse matrices assembled on the host (SciPy): applied in JAX as COO entries padded
to a size class, so that one compiled program serves every matrix whose sizes fall in it;
applied on the host by SciPy, their rows split in blocks whose products run in threads.

Padded entries are zeros at (0, 0), which add exactly nothing to a product, and padded
rows and columns hold no entry, so a padded vector's extra entries stay 0. The products
are gathers and segment sums, the same on any device. Used by the hierarchy's CG solves
(``jurs._fit.adaptive``) and by the device V-cycle (``jurs._linalg.thb_multigrid``)."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import equinox as eqx
import jax
import numpy as np
from jax import Array

from .._problem.sizes import padded_to


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


#: At most this many threads for the host's sparse products (``normal_product``): each
#: thread's transposed product writes a whole coefficient-length vector, so more threads
#: cost memory and a longer sum for products that shrink; measured on two cores only.
MAX_HOST_THREADS = 8


def host_threads() -> int:
    """The threads the host's sparse products use: the CPUs this process may run on, at
    most ``MAX_HOST_THREADS``."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity on this platform
        cpus = os.cpu_count() or 1
    return max(1, min(cpus, MAX_HOST_THREADS))


def row_blocks(matrix, count: int) -> list:
    """A SciPy CSR ``matrix``'s rows in ``count`` contiguous blocks of about equal entries,
    ``[(first row, block)]``, each block a CSR view of the matrix's own arrays: nothing
    is copied."""
    from scipy.sparse import csr_matrix

    bounds = np.searchsorted(matrix.indptr, np.linspace(0, matrix.nnz, count + 1))
    bounds[0], bounds[-1] = 0, matrix.shape[0]
    blocks = []
    for first, last in zip(bounds[:-1], bounds[1:]):
        if last <= first:
            continue
        start, stop = matrix.indptr[first], matrix.indptr[last]
        # Built empty, then given the views: SciPy's constructor copies a view of a much
        # larger array (its prune step), which would copy the whole matrix block by block.
        block = csr_matrix((int(last - first), matrix.shape[1]), dtype=matrix.dtype)
        block.data = matrix.data[start:stop]
        block.indices = matrix.indices[start:stop]
        block.indptr = (matrix.indptr[first : last + 1] - start).astype(matrix.indptr.dtype)
        blocks.append((int(first), block))
    return blocks


@contextmanager
def normal_product(collocation, regulariser, lam: float, row_weights=None, threads=None):
    """``c -> D^T S D c + lam R c`` on the host (float64), for a context: ``D``
    (``collocation``) and ``R`` (``regulariser``) SciPy CSR matrices, ``S`` the rows'
    ``row_weights`` (None: 1). Their rows are split in ``threads`` blocks (``row_blocks``;
    None: ``host_threads``), each block's products in a thread of its own: SciPy's sparse
    products release the GIL, so the blocks run side by side. ``D^T`` is applied as the
    product of ``D``'s transpose view (CSC), with no transposed copy of ``D``."""
    threads = host_threads() if threads is None else max(1, int(threads))
    weights = None if row_weights is None else np.asarray(row_weights, float)
    data = row_blocks(collocation, threads)
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
    with ThreadPoolExecutor(count) as pool:

        def apply(c) -> np.ndarray:
            c = np.asarray(c, float)
            first, *rest = pool.map(lambda k: block(k, c), range(count))
            for part in rest:
                first += part
            return first

        yield apply
