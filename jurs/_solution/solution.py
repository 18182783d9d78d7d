"""What a fit returns: the spline, its metrics, run statistics and a readable verdict."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax import Array

from .._model.adaptive import AdaptiveSpline
from .._model.spline import ImplicitSpline


class RESULTS(eqx.Enumeration):
    """How a run ended. ``jurs.RESULTS[sol.result]`` gives the message."""

    successful = (
        "converged: the solver's stop rule was met (for the paper's iterations "
        "|E_new - E_old| < tol, eq. 38; for a direct solve, the solve succeeded)"
    )
    max_steps_reached = (
        "stopped after max_steps without meeting |E_new - E_old| < tol; Algorithm 1 returns "
        "here too, the result is usable but the energy was still moving"
    )
    failed = (
        "the solver's inner method failed (for example a singular linear system); the "
        "iterate is not certified, see the solver's state for its own verdict"
    )
    nonfinite = (
        "the energy became NaN or Inf; the last finite iterate was kept. For IURS lower tau "
        "or lambda (eq. 33 is stable only for small lambda); for other solvers see their "
        "docstrings"
    )
    inconsistent_normals = (
        "the normals are not consistently oriented: neighbouring normals point to opposite "
        "sides of the curve or surface (part of the cloud flipped), they lie along it (random "
        "normals), every one points inward (the fit of a closed shape is negative outside "
        "it: pass -normals), or the fit's own sign disagrees with the inside/outside "
        "targets at many offset samples (random normals, features narrower than the "
        "noise or the grid, or a lambda so large that the fit cannot follow the data); the "
        "zero set is not a "
        "reconstruction. Orient the normals (all outward) and fit again; see sol.metrics "
        "for the measured fractions: where few normals are flipped against their "
        "neighbours (flipped_normal_fraction, tangential_normal_fraction near 0), the "
        "shape is finer than the fit resolves (a finer grid=, denser or less noisy points)"
    )
    weights_at_floor = (
        "the rational weights were driven to their floor (min_weight) on a large part of "
        "the grid: the weight step tau is far too large for this problem, and the zero set "
        "is degraded. Lower tau (the default 1e-2 suits unit-scale data)"
    )
    doubtful = (
        "the solve succeeded, but checks of the data and of the fit doubt the zero set in "
        "places (features narrower than the grid resolves, data points left far from the "
        "zero set, or closed parts of the zero set the data do not carry); "
        "sol.stats['doubts'] says which and where, and what to change. The fit is "
        "returned as it is"
    )
    weights_at_ceiling = (
        "the rational weights grew past their ceiling (a million times the start's largest): "
        "the weight step tau is absurdly large for this problem, and the weights head for "
        "overflow whatever the energy says. Lower tau (the default 1e-2 suits unit-scale "
        "data)"
    )


#: The short names of the [`RESULTS`][jurs.RESULTS] items, in their order
#: (``Solution.status``).
RESULT_NAMES = (
    "successful",
    "max_steps_reached",
    "failed",
    "nonfinite",
    "inconsistent_normals",
    "weights_at_floor",
    "doubtful",
    "weights_at_ceiling",
)


#: The short name of each [`RESULTS`][jurs.RESULTS]
#: item's index.
_NAME_OF_INDEX = {int(np.asarray(getattr(RESULTS, n)._value)): n for n in RESULT_NAMES}

#: The verdicts that ``throw=True`` raises (as ``equinox.EquinoxRuntimeError``): the fit is
#: not a reconstruction. ``max_steps_reached`` is not one: Algorithm 1 stops there by design
#: (the paper's fixed-step runs) and its iterate is usable; nor is ``doubtful``, a usable fit
#: that [`jurs.fit`][] also warns about.
RAISED_RESULTS = (
    "failed",
    "nonfinite",
    "inconsistent_normals",
    "weights_at_floor",
    "weights_at_ceiling",
)


def unusable(result) -> Any:
    """A boolean (traceable) that is True where ``result`` is one of
    ``RAISED_RESULTS``, and the index of that verdict in it."""
    hits = jnp.stack([result == getattr(RESULTS, name) for name in RAISED_RESULTS])
    return jnp.any(hits), jnp.argmax(hits)


def error_message(name: str) -> str:
    """What ``throw=True`` raises for the verdict ``name``."""
    return (
        f"the fit's verdict is {name}: {RESULTS[getattr(RESULTS, name)]}. Pass throw=False "
        "to get the Solution anyway and read sol.result"
    )


def raise_unless_reconstruction(sol: Solution, throw: bool = True) -> Solution:
    """``sol``, after raising ``equinox.EquinoxRuntimeError`` (``error_message``, then
    each of ``sol.stats["doubts"]`` on a line of its own) where ``throw`` and its verdict
    says it is not a reconstruction (``RAISED_RESULTS``): the one place every fit's
    ``throw=True`` acts. Needs a concrete verdict."""
    if throw and sol.status in RAISED_RESULTS:
        # The doubts say what this fit's checks found (inward normals, normals jurs
        # estimated itself), which the verdict's general text cannot.
        doubts = "".join(f"\n- {doubt}" for doubt in sol.stats.get("doubts") or ())
        raise eqx.EquinoxRuntimeError(error_message(sol.status) + doubts)
    return sol


class Solution(eqx.Module):
    """Result of [`jurs.fit`][] or [`jurs.solve`][].

    Attributes:
        spline: the fitted [`ImplicitSpline`][jurs.ImplicitSpline] (call it on (n, 2)
            points), or [`AdaptiveSpline`][jurs.AdaptiveSpline] from
            [`jurs.fit_adaptive`][].
        metrics: ``E``, ``E_d``, ``R``, ``E_ave``, ``E_max``, ``mu`` (eq. 35-37; see
            [`jurs.internal.metrics`][]) and ``lam``, the lambda that ``E`` uses.
        stats: ``num_steps`` and ``energy_history`` (``max_steps + 1`` entries: the energy
            before the first step and after each step, NaN past ``num_steps``).
        result: a [`RESULTS`][jurs.RESULTS] item; ``sol.message`` reads it.
        state: the solver's final state (for warm starts and inspection).
        settings: the [`jurs.Settings`][] that [`jurs.fit`][] chose automatically, or
            None when every setting was given.
    """

    spline: ImplicitSpline | AdaptiveSpline
    metrics: dict[str, Any]
    stats: dict[str, Any]
    result: RESULTS
    state: Any
    settings: Any = eqx.field(static=True, default=None)

    @property
    def message(self) -> str:
        return RESULTS[self.result]

    @property
    def status(self) -> str:
        """The verdict's short name, one of ``RESULT_NAMES`` (``"successful"``,
        ``"max_steps_reached"``, ...): what scripts and the command line print. Needs a
        concrete result (not inside ``jax.jit``)."""
        # One read of the item's index (a comparison per name dispatches a JAX op each).
        index = int(np.asarray(self.result._value))
        return _NAME_OF_INDEX[index]

    @property
    def succeeded(self) -> Array:
        """Whether the verdict is ``successful``: a boolean scalar array (traceable)."""
        return self.result == RESULTS.successful
