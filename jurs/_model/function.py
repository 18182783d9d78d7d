"""AbstractSpline: the rational implicit function g of eq. 14, whatever its basis.

jurs has two bases for one model: the uniform tensor grid ([`jurs.ImplicitSpline`][]) and
the truncated hierarchical basis ([`jurs.AdaptiveSpline`][]), which refined everywhere to
one level *is* the uniform grid. Every caller outside ``jurs._model`` reaches g through
this interface (the equinox abstract/final pattern: the two concrete classes are final,
each implements the abstract members below), so level sets, verdicts, plots and saving
never ask which basis they hold. What differs between the bases is a method here.
"""

import abc
from typing import TYPE_CHECKING, Any

import equinox as eqx
import numpy as np
from equinox import AbstractVar
from jax import Array
from jaxtyping import ArrayLike, Float


class AbstractSpline(eqx.Module):
    """g of eq. 14 on some basis: ``sum w c B / sum w B``, negative inside the shape and
    positive outside.

    Calling it on ``(n, d)`` points (or one ``(d,)`` point) returns g there, in JAX: jit,
    grad and vmap go through it. The host methods (``lattice``, ``on_host``,
    ``band_lattice``, ``values_and_gradients``, ``slope_bound``) evaluate in float64
    NumPy, compiling nothing, for meshing, contouring and verdicts.

    Attributes:
        control: the coefficients C (a grid, or one per active function).
        weights: their weights w (eq. 14), positive.
        lower, upper: ``(d,)`` corners of the box the basis spans.
    """

    # Declared for equinox (each subclass provides them, as fields or properties); hidden
    # from the type checker, which would otherwise put them first among every subclass's
    # fields, where the concrete classes order their own.
    if not TYPE_CHECKING:
        control: AbstractVar[Array]
        weights: AbstractVar[Array]
        lower: AbstractVar[Array]
        upper: AbstractVar[Array]
    else:

        @property
        def control(self) -> Array: ...
        @property
        def weights(self) -> Array: ...
        @property
        def lower(self) -> Array: ...
        @property
        def upper(self) -> Array: ...

    @property
    @abc.abstractmethod
    def ndim(self) -> int:
        """2 for a curve's g(x, y), 3 for a surface's g(x, y, z)."""

    @property
    @abc.abstractmethod
    def cell_widths(self) -> np.ndarray:
        """``(d,)`` float64: the sides of a finest cell (a knot span of the grid, or a cell
        of the hierarchy's finest level), on the host."""

    @property
    def cell_width(self) -> float:
        """The widest side of a finest cell, on the host: the length below which the
        spline cannot follow a shape."""
        return float(np.max(self.cell_widths))

    @property
    @abc.abstractmethod
    def finest_cells(self) -> tuple[int, ...]:
        """Cells per axis of the finest level over the whole box (for the grid, its knot
        spans ``N - 3``)."""

    @abc.abstractmethod
    def __call__(self, xy: Float[ArrayLike, "*n d"]) -> Float[Array, "*n"]:
        """g at ``xy`` (eq. 14)."""

    @abc.abstractmethod
    def grad(self, xy: Float[ArrayLike, "*n d"]) -> Float[Array, "*n d"]:
        """The spatial gradient of g at ``xy``: ``(n, d)``, or ``(d,)`` for one point."""

    @abc.abstractmethod
    def lattice(self, axes) -> np.ndarray:
        """g at every node of the tensor lattice ``axes = (xs, ys[, zs])``, "ij"
        indexing, float64 on the host."""

    @abc.abstractmethod
    def on_host(self) -> Any:
        """An evaluator of g on the host, built once for many evaluations: an object whose
        ``lattice(axes)`` and ``values(points)`` are this spline's (float64 NumPy), without
        converting the coefficients (or cascading them) again for each."""

    @abc.abstractmethod
    def band_lattice(self, axes, level: float) -> tuple[np.ndarray, np.ndarray]:
        """``(values, evaluated)`` on the lattice ``axes``: nodes marked ``evaluated``
        hold g; every other node lies in a region strictly on one side of ``level`` and
        holds a value of g from that side, so that the signs of ``values - level`` and
        the contours of ``values`` are the full lattice's. The grid evaluates every
        node; the hierarchy only the blocks where its level set can be
        (``jurs._model.band``)."""

    @abc.abstractmethod
    def values_and_gradients(
        self, points: Float[ArrayLike, "n d"], *, chunk: int = 1 << 14
    ) -> tuple[Float[np.ndarray, " n"], Float[np.ndarray, "n d"]]:
        """g and its spatial gradient at scattered ``points``, float64 on the host."""

    @abc.abstractmethod
    def slope_bound(self) -> Float[np.ndarray, " d"]:
        """A scale of ``|dg/dx_a|`` per axis, on the host (a bound for weights 1): how far
        g can change over one lattice step, for the meshing's nudge."""

    def coefficients(self) -> tuple[np.ndarray, np.ndarray]:
        """``(control, weights)`` as float64 NumPy arrays (grids, or vectors over the
        active functions)."""
        return np.asarray(self.control, np.float64), np.asarray(self.weights, np.float64)
