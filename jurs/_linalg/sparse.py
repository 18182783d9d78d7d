"""Sparse matrices assembled on the host (SciPy) and applied in JAX: COO entries padded
to a size class, so that one compiled program serves every matrix whose sizes fall in it.

Padded entries are zeros at (0, 0), which add exactly nothing to a product, and padded
rows and columns hold no entry, so a padded vector's extra entries stay 0. The products
are gathers and segment sums, the same on any device. Used by the hierarchy's CG solves
(``jurs._fit.adaptive``) and by the device V-cycle (``jurs._linalg.thb_multigrid``)."""

from __future__ import annotations

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
