"""The block Cholesky factorisation of a 2D stencil system (``BlockCholesky``, a lineax
solver): the exact solve of large curve fits."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import lineax as lx
from jax import Array

from .._model.precision import full_precision
from .stencil import HALF, SIDE, StencilOperator

#: Largest diagonal block that ``_cholesky_and_inverse`` hands to LAPACK. Larger blocks
#: run OpenBLAS's kernels threaded, and those threads compete with XLA's own (slower by
#: orders of magnitude: docs/multigrid.md, "Measurements behind the constants"); they are
#: split recursively into matrix products, which XLA runs itself.
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
#: ``BlockCholesky`` (its factor takes ``32 N M^2`` bytes in float64: 1 GB at
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


class BlockCholesky(lx.AbstractLinearSolver):
    """The direct solve of a ``jurs._linalg.stencil.StencilOperator`` on a 2D grid by
    ``stencil_cholesky_solve``, as a lineax solver.

    No tolerance: the residual is at rounding level. The matrix must be numerically
    positive definite; where it is not, the factorisation breaks down, the solution is
    not finite and the result is ``breakdown``. Differentiable like any lineax solve (the
    adjoint system is solved by the same method).
    """

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]) -> Array:
        del options
        if not isinstance(operator, StencilOperator) or operator.stencil.ndim != 4:
            raise ValueError(
                f"BlockCholesky solves a StencilOperator on a 2D grid, got {type(operator)}"
            )
        return operator.stencil

    def compute(self, state: Array, vector: Array, options: dict[str, Any]):
        del options
        solution = stencil_cholesky_solve(state, vector)
        finite = jnp.all(jnp.isfinite(solution))
        return solution, lx.RESULTS.where(finite, lx.RESULTS.successful, lx.RESULTS.breakdown), {}

    def transpose(self, state: Array, options: dict[str, Any]):
        return state, options  # symmetric

    def conj(self, state: Array, options: dict[str, Any]):
        return state, options  # real

    def assume_full_rank(self) -> bool:
        return True
