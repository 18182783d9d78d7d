"""The rational implicit function g (eq. 14) as an equinox Module.

``g(x) = sum_ij C_ij w_ij B_i(x) B_j(y) / W(x)`` with ``W(x) = sum_kl w_kl B_k(x) B_l(y)``;
with all weights 1, ``W = 1`` (partition of unity) and g is the B-spline f of eq. 2.
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
    tensor_basis,
)


class LocalBasis(eqx.Module):
    """The 16 non-zero B-spline products of each of ``n`` points, and the cell they live in.

    These depend on the points, the box and the grid only, never on C or w, so solvers
    build them once and reuse them every step (only the weights move the rational rows).
    """

    cell: Array  # (n,) int32 flat cell index
    bx: Array  # (n, 4) x-direction basis values
    by: Array  # (n, 4) y-direction basis values

    @property
    def products(self) -> Array:
        """``B_a(x) B_b(y)`` for the 16 local terms; ``(n, 16)``."""
        return tensor_basis(self.bx, self.by)


def local_basis(xy: Array, lower: Array, upper: Array, shape: tuple[int, int]) -> LocalBasis:
    """Evaluate the local basis of the ``(N, M)`` grid on ``[lower, upper]`` at ``xy (n, 2)``."""
    cell, t = locate(xy, lower, upper, shape)
    b = cubic_weights(t)  # (n, 2, 4)
    return LocalBasis(cell=flat_cell(cell, shape), bx=b[:, 0], by=b[:, 1])


def rational_terms(local: LocalBasis, control: Array, weights: Array):
    """Rational evaluation at the points of ``local`` (eq. 14).

    Returns ``(wb, denom, g)``: ``wb = w_ij B_i B_j`` for the 16 local terms ``(n, 16)``,
    ``denom = W(x)`` ``(n,)`` and ``g(x)`` ``(n,)``. The collocation row of eq. 23 is
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
        xy2 = jnp.atleast_2d(xy)
        _, _, g = rational_terms(self.local_basis(xy2), self.control, self.weights)
        return g[0] if single else g

    def grad(self, xy: Array) -> Array:
        """Spatial gradient of g at ``xy (n, 2)``; ``(n, 2)`` (or ``(2,)`` for one point)."""
        xy = jnp.asarray(xy)
        point_grad = jax.grad(lambda p: self(p))
        return point_grad(xy) if xy.ndim == 1 else jax.vmap(point_grad)(xy)
