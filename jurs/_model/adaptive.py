"""AdaptiveSpline: the rational implicit function of eq. 14 on a THB hierarchy.

``g(x) = sum_tau w_tau c_tau tau(x) / sum_tau w_tau tau(x)`` over the active functions
``tau`` of a ``jurs._model.hierarchy.Hierarchy``; with every weight 1 the denominator is 1
(the truncated basis is a partition of unity) and g is the hierarchical B-spline itself.
Both are a [`jurs.AbstractSpline`][] (``g(xy)``, ``g.grad(xy)``, ``lower``, ``upper``,
the host evaluations), so the level-set tools and plots take either.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.core import Tracer
from jaxtyping import ArrayLike, Float

from .._kept import KeptByIdentity
from .band import band_lattice
from .finest import level_offsets
from .function import AbstractSpline
from .hierarchy import Hierarchy, unravel_keys
from .lattice import FinestSpline, adaptive_lattice_values, finest_values_and_gradients
from .leaves import (
    hierarchy_values,
    hierarchy_values_and_gradients,
    rational_values_and_gradients,
)
from .precision import on_device

#: The host evaluator (``FinestSpline``: the cascade to the finest level, done once) of
#: each live AdaptiveSpline, by identity: a spline of JAX arrays is immutable, and its
#: meshing, verdicts and evaluations at points all read the same one (one of NumPy
#: arrays, which can change in place, gets a new one each time). An entry goes with its
#: spline.
_EVALUATORS = KeptByIdentity()


def _host_points(spline: AdaptiveSpline, xy) -> np.ndarray | None:
    """``xy`` as a float64 ``(n, d)`` or ``(d,)`` host array where ``spline(xy)`` can run
    on the host: no leaf traced (``jax.grad``, ``vmap`` or ``jit`` of the spline or the
    points go through the hierarchy, differentiably), a shape it takes, not empty. None
    otherwise (then the traced path evaluates, and reports bad shapes as it does)."""
    leaves = (spline.control, spline.weights, xy)
    if any(isinstance(leaf, Tracer) for leaf in leaves):
        return None
    try:
        x = np.asarray(xy, np.float64)
    except (TypeError, ValueError):
        return None
    d = spline.ndim
    if x.shape == (d,) or (x.ndim == 2 and x.shape[1] == d and len(x) > 0):
        return x
    return None


class AdaptiveSpline(AbstractSpline):
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
    def cell_widths(self) -> np.ndarray:
        """The sides of a finest-level cell, on the host."""
        finest = self.hierarchy.num_levels - 1
        return np.asarray(self.hierarchy.cell_width(finest, np), np.float64)

    @property
    def finest_cells(self) -> tuple[int, ...]:
        """Cells per axis of the finest level over the whole box (the uniform grid the
        hierarchy stands in for)."""
        return self.hierarchy.cells(self.hierarchy.num_levels - 1)

    def _result_dtype(self, xy):
        return jnp.result_type(self.control.dtype, getattr(xy, "dtype", float))

    def __call__(self, xy: Float[ArrayLike, "*n d"]) -> Float[Array, "*n"]:
        x = _host_points(self, xy)
        if x is not None:  # concrete: on the host, nothing to compile for a new fit
            g, _ = finest_values_and_gradients(self.on_host(), np.atleast_2d(x), gradients=False)
            return on_device(g[0] if x.ndim == 1 else g, self._result_dtype(xy))
        xy = jnp.asarray(xy)
        single = xy.ndim == 1
        both = hierarchy_values(
            self.hierarchy,
            jnp.stack([self.weights * self.control, self.weights]),
            jnp.atleast_2d(xy),
        )
        g = both[0] / both[1]  # eq. 14
        return g[0] if single else g

    def grad(self, xy: Float[ArrayLike, "*n d"]) -> Float[Array, "*n d"]:
        """Spatial gradient of g at ``xy (n, d)``; ``(n, d)`` (or ``(d,)`` for one point):
        the quotient rule on eq. 14."""
        x = _host_points(self, xy)
        if x is not None:
            _, slope = finest_values_and_gradients(self.on_host(), np.atleast_2d(x))
            assert slope is not None
            return on_device(slope[0] if x.ndim == 1 else slope, self._result_dtype(xy))
        xy = jnp.asarray(xy)
        single = xy.ndim == 1
        x = jnp.atleast_2d(xy)
        # One leaf search and one cascade for numerator and denominator together.
        both, slopes = hierarchy_values_and_gradients(
            self.hierarchy, jnp.stack([self.weights * self.control, self.weights]), x
        )
        out = rational_values_and_gradients(both, slopes)[1]
        return out[0] if single else out

    def lattice(self, axes) -> np.ndarray:
        """g on the tensor lattice ``axes`` through the finest level's coefficients, computed
        only where the lattice needs them (``jurs._model.lattice.FinestSpline``)."""
        return adaptive_lattice_values(self, axes)

    def on_host(self) -> FinestSpline:
        """The finest level's reader (``jurs._model.lattice.FinestSpline``: the cascade
        done once; see [`jurs.AbstractSpline`][]), kept while the spline lives: every
        host evaluation of this spline (points, lattices, band meshes, verdicts) reads
        the same one."""
        if not all(isinstance(a, jax.Array) for a in (self.control, self.weights)):
            return FinestSpline(self)
        return _EVALUATORS.get(self, FinestSpline)

    def band_lattice(self, axes, level: float) -> tuple[np.ndarray, np.ndarray]:
        """``(values, evaluated)``: g only on the blocks of the lattice where the level set
        can be (``jurs._model.band.band_lattice``; see [`jurs.AbstractSpline`][])."""
        values, evaluated, _ = band_lattice(self.on_host(), axes, float(level))
        return values, evaluated

    def values_and_gradients(
        self, points: Float[ArrayLike, "n d"], *, chunk: int = 1 << 14
    ) -> tuple[Float[np.ndarray, " n"], Float[np.ndarray, "n d"]]:
        """g and its gradient at ``points`` on the host, through the finest level's
        coefficients under them (nothing compiled)."""
        values, gradients = finest_values_and_gradients(self.on_host(), points, chunk=chunk)
        assert gradients is not None
        return values, gradients

    def slope_bound(self) -> Float[np.ndarray, " d"]:
        """The grid's bound (``ImplicitSpline.slope_bound``) over the levels: on each leaf
        of level ``l`` g is the level's B-spline with cascaded coefficients ``a^l``
        (``jurs._model.hierarchy.cascade``), so the same bound holds with the differences of
        ``a^l`` between neighbours over a leaf of level ``l`` (the regulariser's pairs,
        ``Hierarchy.edges``), over ``h_l``, the largest over the levels."""
        return finest_slope_bound(self)


def finest_slope_bound(spline: AdaptiveSpline, evaluator: FinestSpline | None = None) -> np.ndarray:
    """``AdaptiveSpline.slope_bound``, its cascaded coefficients read from ``evaluator``
    where one was built already; ``(d,)``."""
    hierarchy = spline.hierarchy
    cascaded = (evaluator or spline.on_host()).cascaded
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = cascaded[0] / cascaded[1]
    starts = level_offsets(hierarchy)
    _, weights = spline.coefficients()
    bound = np.zeros(hierarchy.ndim)
    for lev in range(hierarchy.num_levels):
        pairs = np.asarray(hierarchy.edges[lev], np.int64)
        if len(pairs) == 0:
            continue
        keys = np.asarray(hierarchy.function_keys[lev], np.int64)
        multi = unravel_keys(keys[pairs], hierarchy.functions(lev))  # (p, 2, d)
        axis = np.argmax(np.abs(multi[:, 1] - multi[:, 0]), axis=1)
        step = np.abs(ratio[starts[lev] + pairs[:, 1]] - ratio[starts[lev] + pairs[:, 0]])
        width = np.asarray(hierarchy.cell_width(lev, np), np.float64)
        for a in range(hierarchy.ndim):
            along = step[(axis == a) & np.isfinite(step)]
            if along.size:
                bound[a] = max(bound[a], float(along.max()) / width[a])
    return weights.max() / weights.min() * bound
