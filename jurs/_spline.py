"""The rational implicit function g (eq. 14) as an equinox Module, and the two linear maps
every solver is built from.

``g(x) = sum_ij C_ij w_ij B_i(x) B_j(y) / W(x)`` with ``W(x) = sum_kl w_kl B_k(x) B_l(y)``;
with all weights 1, ``W = 1`` (partition of unity) and g is the B-spline f of eq. 2.

So g is two plain B-spline evaluations, ``F(w C) / F(w)``, where ``F`` maps a coefficient
grid to values at the samples (:func:`bspline_values`). Its transpose ``T``
(:func:`bspline_transpose`) gives everything else: the collocation transpose of eq. 23 is
``D^T v = w * T(v / W)``, and the gradients of DESIGN section 2 are ``T`` of per-sample
scalars times a grid. No (samples x 16) array of rows is ever needed on the fast path.

Samples are stored in *buckets*: runs of ``bucket_size`` samples that share one cell, so a
bucket reads its 4 x 4 coefficient patch once and its sums over samples are dense
reductions instead of scatters. ``bucket_size = 1`` (one sample a bucket, any order) is the
generic layout that works under any JAX transformation.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array

from ._basis import (
    cubic_weights,
    flat_cell,
    grid_to_patches,
    locate,
    num_cells,
    patches_to_grid,
    tensor_basis,
)


class LocalBasis(eqx.Module):
    """The non-zero B-spline values of ``S`` samples and the cell each lives in.

    These depend on the samples, the box and the grid only, never on C or w, so solvers
    build them once and reuse them every step (only the weights move the rational rows).
    Samples come in buckets of ``bucket_size`` consecutive entries sharing one cell.
    """

    cell: Array  # (S,) int32 flat cell index
    bx: Array  # (S, 4) x-direction basis values
    by: Array  # (S, 4) y-direction basis values
    bucket_size: int = eqx.field(static=True, default=1)

    @property
    def num_buckets(self) -> int:
        return self.cell.shape[0] // self.bucket_size

    @property
    def bucket_cell(self) -> Array:
        """The cell of each bucket; ``(num_buckets,)``."""
        return self.cell[:: self.bucket_size]

    @property
    def products(self) -> Array:
        """``B_a(x) B_b(y)`` for the 16 local terms; ``(S, 16)``."""
        return tensor_basis(self.bx, self.by)


def local_basis(xy: Array, lower: Array, upper: Array, shape: tuple[int, int],
                bucket_size: int = 1) -> LocalBasis:
    """The local basis of the ``(N, M)`` grid on ``[lower, upper]`` at ``xy (S, 2)``.

    With ``bucket_size > 1`` the caller guarantees that each run of ``bucket_size``
    consecutive points lies in one cell (see :func:`jurs._problem.bucket_layout`).
    """
    cell, t = locate(xy, lower, upper, shape)
    b = cubic_weights(t)  # (S, 2, 4)
    return LocalBasis(cell=flat_cell(cell, shape), bx=b[:, 0], by=b[:, 1], bucket_size=bucket_size)


def _bucketed(local: LocalBasis):
    k = local.bucket_size
    nb = local.num_buckets
    return local.bx.reshape(nb, k, 4), local.by.reshape(nb, k, 4)


def bspline_values(local: LocalBasis, grids: Array) -> Array:
    """F: the B-spline ``sum_ij G_ij B_i B_j`` of coefficient grid(s) at the samples.

    ``grids`` is ``(..., N, M)``; returns ``(..., S)``.
    """
    if grids.ndim > 2:
        # One grid at a time: XLA's CPU batched matmul is several times slower with an
        # extra batch axis here than two separate calls (measured).
        flat = grids.reshape((-1,) + grids.shape[-2:])
        values = jnp.stack([bspline_values(local, g) for g in flat])
        return values.reshape(grids.shape[:-2] + values.shape[-1:])
    patches = grid_to_patches(grids)[local.bucket_cell].reshape(local.num_buckets, 4, 4)
    bx, by = _bucketed(local)
    along_y = jnp.einsum("bka,bac->bkc", bx, patches)  # batched (K x 4) @ (4 x 4)
    return jnp.sum(along_y * by, axis=-1).reshape(-1)


def bspline_transpose(local: LocalBasis, values: Array, shape: tuple[int, int]) -> Array:
    """T, the transpose of :func:`bspline_values`: ``sum_k v_k B_i B_j(x_k)`` on the grid.

    ``values`` is ``(..., S)``; returns ``(..., N, M)``. Several value vectors share one
    pass over the samples.
    """
    lead = values.shape[:-1]
    bx, by = _bucketed(local)
    v = values.reshape(lead + (local.num_buckets, local.bucket_size))
    per_bucket = jnp.einsum("...bk,bka,bkc->b...ac", v, bx, by)
    per_bucket = per_bucket.reshape((local.num_buckets,) + lead + (16,))
    per_cell = jax.ops.segment_sum(per_bucket, local.bucket_cell, num_segments=num_cells(shape))
    return patches_to_grid(jnp.moveaxis(per_cell, 0, -2), shape)


def rational_values(local: LocalBasis, control: Array, weights: Array):
    """``(W, g)`` at the samples: ``W = F(w)`` and ``g = F(w C) / W`` (eq. 14)."""
    both = bspline_values(local, jnp.stack([weights, weights * control]))
    return both[0], both[1] / both[0]


def rational_terms(local: LocalBasis, control: Array, weights: Array):
    """Rational evaluation with explicit rows (eq. 14 and 23), for checks and row-based
    algorithms; the solvers use the cheaper :func:`rational_values`.

    Returns ``(wb, denom, g)``: ``wb = w_ij B_i B_j`` for the 16 local terms ``(S, 16)``,
    ``denom = W(x)`` ``(S,)`` and ``g(x)`` ``(S,)``. The collocation row of eq. 23 is
    ``wb / denom``.
    """
    w_rows = grid_to_patches(weights)[local.cell]
    c_rows = grid_to_patches(control)[local.cell]
    wb = local.products * w_rows
    denom = jnp.sum(wb, axis=-1)
    g = jnp.sum(wb * c_rows, axis=-1) / denom
    return wb, denom, g


class ImplicitSpline(eqx.Module):
    """A uniform rational cubic spline function on the box ``[lower, upper]``.

    Fields: ``control`` (N, M) coefficients C, ``weights`` (N, M) positive weights w, and the
    box corners ``lower``/``upper`` (2,), which fix the uniform knots. Calling it on an
    ``(n, 2)`` array (or one ``(2,)`` point) returns g there (eq. 14). It is a pytree: jit,
    grad and vmap go through it. Outside the box the border polynomial pieces extend.
    """

    control: Array
    weights: Array
    lower: Array
    upper: Array

    def __check_init__(self):
        if self.control.ndim != 2 or self.control.shape != self.weights.shape:
            raise ValueError(
                f"control and weights must be matching 2D grids, got {self.control.shape} "
                f"and {self.weights.shape}"
            )
        if min(self.control.shape) < 4:
            raise ValueError(f"grid must be at least 4 x 4 for cubic splines, got {self.control.shape}")

    @property
    def shape(self) -> tuple[int, int]:
        return self.control.shape

    @classmethod
    def bspline(cls, control: Array, lower, upper) -> "ImplicitSpline":
        """A polynomial B-spline (all weights 1)."""
        control = jnp.asarray(control)
        return cls(control, jnp.ones_like(control), jnp.asarray(lower, control.dtype),
                   jnp.asarray(upper, control.dtype))

    def local_basis(self, xy: Array) -> LocalBasis:
        return local_basis(xy, self.lower, self.upper, self.shape)

    def __call__(self, xy: Array) -> Array:
        xy = jnp.asarray(xy)
        single = xy.ndim == 1
        _, g = rational_values(self.local_basis(jnp.atleast_2d(xy)), self.control, self.weights)
        return g[0] if single else g

    def grad(self, xy: Array) -> Array:
        """Spatial gradient of g at ``xy (n, 2)``; ``(n, 2)`` (or ``(2,)`` for one point)."""
        xy = jnp.asarray(xy)
        point_grad = jax.grad(lambda p: self(p))
        return point_grad(xy) if xy.ndim == 1 else jax.vmap(point_grad)(xy)
