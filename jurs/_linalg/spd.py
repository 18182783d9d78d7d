"""Batched inverses of small symmetric positive definite blocks, without LAPACK
(``spd_inverse``): the multigrid's patches and coarsest level, and the block-Jacobi
preconditioner of a stencil (``jurs._linalg.stencil.BlockJacobi``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array

#: Largest block that ``spd_inverse`` factorises column by column (a loop); larger ones
#: are split in halves joined by matrix products. No LAPACK: XLA runs independent kernels
#: concurrently, and concurrent batched LAPACK calls inside a threaded OpenBLAS can
#: deadlock; splitting down to 1 x 1 instead makes the compilation long (docs/multigrid.md,
#: "Measurements behind the constants").
LEAF_BLOCK = 12


def _leaf_cholesky_inverse(a: Array, floor: float) -> Array:
    """``L^-1`` of a batch of small symmetric positive definite ``a = L L^T``: Cholesky by
    columns, then forward substitution, each a loop over the columns with batched vector
    operations. Pivots are clamped at ``floor`` (a block that is not numerically positive
    definite gets a large finite inverse, not NaN)."""
    m = a.shape[-1]
    index = jnp.arange(m)

    def factor(j, carry):
        rest, low = carry
        column = jax.lax.dynamic_index_in_dim(rest, j, axis=-1, keepdims=False)
        pivot = jax.lax.dynamic_index_in_dim(column, j, axis=-1)
        column = jnp.where(index >= j, column * jax.lax.rsqrt(jnp.maximum(pivot, floor)), 0.0)
        rest = rest - column[..., :, None] * column[..., None, :]
        return rest, jax.lax.dynamic_update_index_in_dim(low, column[..., None], j, axis=-1)

    _, low = jax.lax.fori_loop(0, m, factor, (a, jnp.zeros_like(a)))

    def substitute(j, inverse):  # row j of L^-1: (e_j - L[j, :j] L^-1[:j]) / L[j, j]
        row = jax.lax.dynamic_index_in_dim(low, j, axis=-2, keepdims=False)
        pivot = jax.lax.dynamic_index_in_dim(row, j, axis=-1)
        unit = (index == j).astype(a.dtype)
        new = (unit - jnp.einsum("...i,...ij->...j", row, inverse)) / pivot
        return jax.lax.dynamic_update_index_in_dim(inverse, new[..., None, :], j, axis=-2)

    return jax.lax.fori_loop(0, m, substitute, jnp.zeros_like(a))


def _cholesky_inverse(a: Array, floor: float) -> Array:
    """``L^-1`` (lower triangular) of a batch of symmetric positive definite ``a = L L^T``,
    recursively by halves: ``L^-1 = [[L1^-1, 0], [-L2^-1 B L1^-1, L2^-1]]`` with
    ``B = A21 L1^-T`` and ``L2 L2^T = A22 - B B^T``; pivots clamped at ``floor``."""
    n = a.shape[-1]
    if n <= LEAF_BLOCK:
        return _leaf_cholesky_inverse(a, floor)
    h = n // 2
    i1 = _cholesky_inverse(a[..., :h, :h], floor)
    b = a[..., h:, :h] @ jnp.swapaxes(i1, -1, -2)
    i2 = _cholesky_inverse(a[..., h:, h:] - b @ jnp.swapaxes(b, -1, -2), floor)
    top = jnp.concatenate([i1, jnp.zeros(i1.shape[:-1] + (n - h,), a.dtype)], axis=-1)
    return jnp.concatenate([top, jnp.concatenate([-(i2 @ b) @ i1, i2], axis=-1)], axis=-2)


def spd_inverse(blocks: Array, ridge: float) -> Array:
    """``(D^1/2 (S + ridge I) D^1/2)^-1`` for a batch of symmetric positive semi-definite
    ``blocks = D^1/2 S D^1/2`` (D the diagonal, S unit-diagonal): the ridge is relative to
    each diagonal entry, and Cholesky's rounding is relative to them too. Pivots below the
    ridge are raised to it; a zero row is inverted as an identity row."""
    diag = jnp.diagonal(blocks, axis1=-2, axis2=-1)
    scale = jax.lax.rsqrt(jnp.where(diag > 0, diag, 1.0))
    unit = blocks * scale[..., :, None] * scale[..., None, :]
    eye = jnp.eye(blocks.shape[-1], dtype=blocks.dtype)
    unit = unit + jnp.where(diag > 0, 0.0, 1.0)[..., None, :] * eye
    low_inv = _cholesky_inverse(unit + ridge * eye, ridge)
    inverse = jnp.swapaxes(low_inv, -1, -2) @ low_inv
    return inverse * scale[..., :, None] * scale[..., None, :]
