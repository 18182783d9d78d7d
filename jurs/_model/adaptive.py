"""AdaptiveSpline: the rational implicit function of eq. 14 on a THB hierarchy.

``g(x) = sum_tau w_tau c_tau tau(x) / sum_tau w_tau tau(x)`` over the active functions
``tau`` of a ``jurs._model.hierarchy.Hierarchy``; with every weight 1 the denominator is 1
(the truncated basis is a partition of unity) and g is the hierarchical B-spline itself.
It evaluates like [`jurs.ImplicitSpline`][] (``g(xy)``, ``g.grad(xy)``, ``lower``,
``upper``), so the level-set tools and plots take either.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Float

from .hierarchy import Hierarchy
from .leaves import (
    hierarchy_values,
    hierarchy_values_and_gradients,
    rational_values_and_gradients,
)
from .packed import packed_gradients_at, packed_values_at

# Traced evaluations (jurs._model.packed takes the others): one compiled program per
# hierarchy and point count. Run eagerly, the leaf search and the
# cascade compile each of their few dozen operations for every new shape (a first
# gradient took over three times as long; docs/performance.md), and a warm call is
# several times slower.
_values = jax.jit(hierarchy_values)
_values_and_gradients = jax.jit(hierarchy_values_and_gradients)


class AdaptiveSpline(eqx.Module):
    """A rational spline on a truncated hierarchical B-spline basis (fine cells near the
    data, coarse elsewhere; see [`jurs.fit_adaptive`][]).

    Attributes:
        hierarchy: the levels, leaves and active functions.
        control: ``(n,)`` coefficients of the active functions, level 0 first.
        weights: ``(n,)`` their weights (eq. 14); all 1 for a polynomial spline.
    """

    hierarchy: Hierarchy
    control: Array
    weights: Array

    def __check_init__(self):
        n = self.hierarchy.num_active
        if self.control.shape != (n,) or self.weights.shape != (n,):
            raise ValueError(
                f"an adaptive spline on {n} active functions needs control and weights of "
                f"shape ({n},), got {self.control.shape} and {self.weights.shape}"
            )

    @property
    def lower(self) -> Array:
        return self.hierarchy.lower

    @property
    def upper(self) -> Array:
        return self.hierarchy.upper

    @property
    def ndim(self) -> int:
        return self.hierarchy.ndim

    @property
    def levels(self) -> int:
        return self.hierarchy.num_levels

    @property
    def cell_width(self) -> float:
        """The widest side of a finest-level cell, on the host: the length below which the
        spline cannot follow a shape."""
        finest = self.hierarchy.num_levels - 1
        return float(np.max(np.asarray(self.hierarchy.cell_width(finest))))

    @property
    def finest_cells(self) -> tuple[int, ...]:
        """Cells per axis of the finest level over the whole box (the uniform grid the
        hierarchy stands in for)."""
        return self.hierarchy.cells(self.hierarchy.num_levels - 1)

    def __call__(self, xy: Float[ArrayLike, "*n d"]) -> Float[Array, "*n"]:
        packed = packed_values_at(self.hierarchy, self.control, self.weights, xy)
        if packed is not None:  # outside any transformation: one program per size class
            return packed
        xy = jnp.asarray(xy)
        single = xy.ndim == 1
        both = _values(
            self.hierarchy,
            jnp.stack([self.weights * self.control, self.weights]),
            jnp.atleast_2d(xy),
        )
        g = both[0] / both[1]  # eq. 14
        return g[0] if single else g

    def grad(self, xy: Float[ArrayLike, "*n d"]) -> Float[Array, "*n d"]:
        """Spatial gradient of g at ``xy (n, d)``; ``(n, d)`` (or ``(d,)`` for one point):
        the quotient rule on eq. 14."""
        packed = packed_gradients_at(self.hierarchy, self.control, self.weights, xy)
        if packed is not None:
            return packed
        xy = jnp.asarray(xy)
        single = xy.ndim == 1
        x = jnp.atleast_2d(xy)
        # One leaf search and one cascade for numerator and denominator together.
        both, slopes = _values_and_gradients(
            self.hierarchy, jnp.stack([self.weights * self.control, self.weights]), x
        )
        out = rational_values_and_gradients(both, slopes)[1]
        return out[0] if single else out
