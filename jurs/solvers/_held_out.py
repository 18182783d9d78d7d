"""HeldOutLeastSquares: the exact solve, with lambda chosen by the error on held-out points."""

from __future__ import annotations

from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jax import Array
from jax.core import Tracer

from .._linalg.normal import DEFAULT_CHUNK, NormalEquations, normal_equations
from .._model.spline import ImplicitSpline, bspline_values
from .._problem.energy import objective
from .._problem.problem import Problem, values_by_point
from .._problem.validate import check_nonnegative
from ._base import AbstractSolver
from ._least_squares import DEFAULT_RIDGE, LeastSquares, LeastSquaresState
from ._robust import slot_points

#: The golden ratio's fractional part: point i is held out where ``frac((i + 1) * PHI) <
#: holdout``, which spreads the held-out points evenly over any stretch of the point order
#: (a traced outline is ordered along the curve) without a random generator.
PHI = 0.6180339887498949


#: Default fraction of the points held out.
DEFAULT_HOLDOUT = 0.2
#: The early stop's rise: the search stops at a candidate scoring more than this fraction
#: worse than the one before. On the real-data benchmark's held-out runs the first rise
#: was 8-52 % where the smallest candidate won (clean, uneven and outlier outlines) and
#: 0.2-5 % on noisy ones, where the scores lie flat before falling: horse at 1 % noise
#: (benchmarks/quality.py) rose 0.15 % from 1e-6 to 1e-5 and fell 6 % at 1e-4, and a stop
#: at the first rise kept 1e-6 and four components for one. Trying on costs solves, never
#: accuracy (the best score tried wins).
EARLY_STOP_RISE = 0.05


def held_out_points(num_points: int, holdout, xp=jnp) -> Array:
    """``(num_points,)`` booleans: the points
    [`HeldOutLeastSquares`][jurs.HeldOutLeastSquares] holds out."""
    return xp.mod((xp.arange(num_points) + 1) * PHI, 1.0) < holdout


def held_out_distance(problem: Problem, values: Array, point_held: Array) -> Array:
    """Mean squared distance of the held-out points to the zero sets of fits whose values
    at the slots are ``values`` (``(candidates, S)``), each distance capped at d.

    The distance of point i is ``|g(P_i)| / slope_i`` with the slope across the curve
    read off its own offset samples, ``(g(P_i + d n_i) - g(P_i - d n_i)) / 2d`` (one
    evaluation pass, no gradient): the first-order distance to the zero set, the quantity a
    reconstruction is judged by. Cap: a fit that reads the point's inside and outside the
    wrong way round (a slope <= 0), or passes farther than d from it, counts d, so that
    one stray point cannot outweigh the rest."""
    m, d = problem.num_points, problem.offset
    point = slot_points(problem)
    real = problem.mask > 0
    g_point, g_out, g_in = jax.vmap(lambda v: values_by_point(v, problem.sample_index, real, m))(
        values
    )
    distance = capped_distance(g_point, g_out, g_in, d)
    counted = point_held & (jax.ops.segment_sum(problem.is_data * problem.mask, point, m) > 0)
    total = jnp.sum(jnp.where(counted, distance * distance, 0.0), axis=-1)
    return total / jnp.maximum(jnp.sum(counted), 1)


def capped_distance(g_point, g_out, g_in, offset, xp=jnp):
    """Each point's first-order distance to the zero set, ``|g(P)| / slope`` with the
    slope across the curve read off its offset samples, ``(g(P + d n) - g(P - d n)) /
    2d``, capped at the offset d; a slope <= 0 (inside and outside read the wrong way
    round) counts d. ``held_out_distance``'s measure on either basis; ``xp=numpy`` on
    the host."""
    slope = (g_out - g_in) / (2.0 * offset)
    distance = xp.where(slope > 0, xp.abs(g_point) / xp.where(slope > 0, slope, 1.0), offset)
    return xp.minimum(distance, offset)


def select_lam(
    problem: Problem,
    candidates: Array,
    holdout=DEFAULT_HOLDOUT,
    exact: LeastSquares | None = None,
    start: Array | None = None,
    early_stop: bool = True,
) -> tuple[Array, Array]:
    """``(lam, scores)``: the candidate (objective's lambda, w = 1) whose fit of the kept
    points puts the held-out points (``held_out_points``) nearest its zero set, and
    every candidate's ``held_out_distance`` (NaN for candidates not tried). See
    [`HeldOutLeastSquares`][jurs.HeldOutLeastSquares], whose ``early_stop`` this is.

    ``exact`` solves each candidate (default ``LeastSquares()``'s linear solvers) from
    ``start`` (default 0)."""
    return _selected(problem, candidates, holdout, exact, start, early_stop)[:2]


def _selected(problem: Problem, candidates, holdout, exact, start, early_stop: bool):
    """``select_lam``'s ``(lam, scores)`` and the normal equations of all the points
    (assembled there in two parts; the final fit needs no new pass)."""
    exact = LeastSquares() if exact is None else exact
    dtype = problem.samples.dtype
    start = jnp.zeros(problem.shape, dtype) if start is None else start
    candidates = jnp.asarray(candidates).astype(dtype)
    point_held = held_out_points(problem.num_points, holdout)
    held = point_held[slot_points(problem)]
    parts = [eqx.tree_at(lambda p: p.mask, problem, problem.mask * w) for w in (~held, held)]
    kept, out = (normal_equations(p, chunk_size=exact.chunk_size) for p in parts)
    # The kept points' share of the (weighted) data, for the kept fits' lambda.
    share = jnp.sum(parts[0].mask * problem.is_data) / jnp.maximum(
        jnp.sum(problem.mask * problem.is_data), 1e-300
    )
    # The choice is discrete: no tangent enters the search (a while loop has no reverse
    # mode), only the final fit at the chosen lambda carries gradients.
    search = jax.lax.stop_gradient((problem, parts[0], kept, share, start, candidates))
    scores = _scores(*search, point_held, exact, early_stop)
    best = jnp.argmin(jnp.where(jnp.isnan(scores), jnp.inf, scores))
    lam = jax.lax.stop_gradient(candidates[best])
    return lam, scores, _union(kept, out)


def stops_search(score, previous):
    """Whether a candidate's held-out ``score`` ends the early-stopping search: more
    than ``EARLY_STOP_RISE`` above the ``previous`` candidate's."""
    return score > previous * (1.0 + EARLY_STOP_RISE)


def _scores(problem, kept_problem, kept, share, start, candidates, point_held, exact, early):
    """Each candidate's held-out score, one solve at a time (the candidates'
    factorisations are never held at once), in the given order; with ``early`` the search
    stops at the first candidate that scores worse than the one before it by more than
    ``EARLY_STOP_RISE``, and the rest stay NaN.

    Why stopping there is safe: the score is the held-out points' distance to the fit's
    zero set, and it measured unimodal in lambda (one minimum, decades apart) on all 52
    runs of the real-data benchmark that chose by held-out points (clean, noisy, uneven and
    outlier clouds); clean clouds, whose minimum is the first candidate, need two solves
    instead of four."""

    def score(lam):
        control = exact.solve_assembled(kept_problem, kept, lam * share, start)[0]
        values = bspline_values(problem.local, control[None])
        return held_out_distance(problem, values, point_held)[0]

    count = candidates.shape[0]

    def going(carry):
        i, scores = carry
        last, before = scores[jnp.maximum(i - 1, 0)], scores[jnp.maximum(i - 2, 0)]
        rose = (i >= 2) & stops_search(last, before)
        return (i < count) & ~(early & rose)

    def step(carry):
        i, scores = carry
        return i + 1, scores.at[i].set(score(candidates[i]))

    initial = (jnp.asarray(0), jnp.full(candidates.shape, jnp.nan, candidates.dtype))
    return jax.lax.while_loop(going, step, initial)[1]


class HeldOutLeastSquaresState(eqx.Module):
    control: Array  # C, the fit of all points at the chosen lambda
    lam: Array  # the chosen lambda
    scores: Array  # (candidates,) held-out error of each candidate's fit (NaN: not tried)
    done: Array  # bool: the solve has run
    result: lx.RESULTS  # the final linear solve's verdict


def _union(normal_a: NormalEquations, normal_b: NormalEquations) -> NormalEquations:
    """The normal equations of the union of two disjoint sample sets."""
    return jax.tree_util.tree_map(jnp.add, normal_a, normal_b)


class HeldOutLeastSquares(AbstractSolver[HeldOutLeastSquaresState]):
    """The exact solve of [`LeastSquares`][jurs.LeastSquares], with lambda chosen among
    the candidates ``lam`` by the data: the one whose fit best predicts points it was not
    given (hold-out validation).

    A fraction ``holdout`` of the points (with their two offset samples) is set aside,
    spread evenly over the point order (``held_out_points``). For every candidate the
    remaining points are fitted and scored by the held-out points' mean squared distance
    to the fit's zero set (``held_out_distance``; not by their residuals of eq. 16,
    which a flatter g lowers: scored that way, noisy clouds chose the smallest lambda).
    The candidate with the lowest score is refitted on all points, and that fit is the
    result (``sol.state.lam``, ``sol.metrics["lam"]``; ``sol.state.scores`` holds every
    candidate's score).

    Why it tells structure from noise: a held-out point that lies on the curve the other
    points trace (a pixel staircase sampled finer than its steps, polygon corners, uneven
    spacing) is predicted best by the fit that follows them closely, so a small lambda
    wins; one displaced by independent noise is predicted best by a fit that averages its
    neighbours, so a larger lambda wins. The normal equations are assembled once per part
    (held out and kept, ``D^T D`` being a sum over samples); each candidate then costs one
    linear solve.

    The candidates are tried in the given order. With ``early_stop`` (the default) they
    must ascend, and the search stops at the first one that scores more than
    ``EARLY_STOP_RISE`` (5 %) worse than the one before it (past such a rise the score
    measured unimodal in lambda on every real-data run; a structured cloud then costs two
    solves, not one per candidate); the candidates not tried score NaN.

    The kept points' lambda is the candidate scaled by their share of the points, so that
    the mean squared residual and the regulariser keep the balance the candidate gives the
    whole cloud (the scale-free lambda of [`jurs.auto_settings`][] grows with the number
    of samples).

    Args:
        lam: the candidate lambdas of the objective (``E_d + lam R``, as
            [`LeastSquares`][jurs.LeastSquares]), a 1-D array; the chosen one is
            ``sol.state.lam``.
        holdout: fraction of the points held out, in (0, 0.5].
        early_stop: stop at the first candidate scoring more than ``EARLY_STOP_RISE``
            worse than the one before (the candidates must then ascend); False tries
            every candidate.
        chunk_size, ridge, linear_solver: as [`LeastSquares`][jurs.LeastSquares].

    Polynomial B-splines (w = 1); one driver step. The choice is discrete: gradients flow
    through the final solve at the chosen lambda, not through the choice. On the adaptive
    basis (``jurs.fit(..., basis="adaptive", solver=...)``) the same search runs on the
    host with the hierarchy's solves (not differentiated there).
    """

    lam: Any = eqx.field(converter=jnp.asarray)
    holdout: float = DEFAULT_HOLDOUT
    early_stop: bool = eqx.field(static=True, default=True)
    linear_solver: lx.AbstractLinearSolver | None = None
    chunk_size: int = eqx.field(static=True, default=DEFAULT_CHUNK)
    ridge: float = DEFAULT_RIDGE

    max_steps: ClassVar[int] = 1
    tol: ClassVar[float] = 0.0
    reassociation_safe: ClassVar[bool] = True
    chooses_lam: ClassVar[bool] = True

    def __check_init__(self):
        lam = self.lam
        if lam.ndim != 1 or lam.shape[0] < 1:
            raise ValueError(f"lam must be a 1-D array of candidates, got shape {lam.shape}")
        if not isinstance(lam, Tracer):
            if not np.all(np.isfinite(lam)) or np.any(np.asarray(lam) < 0):
                raise ValueError("lam must hold finite candidates >= 0")
        if self.early_stop and not isinstance(lam, Tracer) and np.any(np.diff(lam) <= 0):
            raise ValueError(
                "with early_stop=True the lam candidates must ascend (the search stops at "
                "the first that scores worse than the one before); sort them or pass "
                "early_stop=False"
            )
        check_nonnegative("holdout", self.holdout, strict=True)
        if not isinstance(self.holdout, Tracer) and not self.holdout <= 0.5:
            raise ValueError(f"holdout must be in (0, 0.5], got {self.holdout}")
        self._exact()

    def fitted_lam(self, state: HeldOutLeastSquaresState) -> Array:
        return state.lam

    def _exact(self) -> LeastSquares:
        return LeastSquares(
            lam=0.0, linear_solver=self.linear_solver, chunk_size=self.chunk_size, ridge=self.ridge
        )

    def init(self, problem: Problem, spline: ImplicitSpline):
        dtype = spline.control.dtype
        lam = self.lam[0].astype(dtype)
        state = HeldOutLeastSquaresState(
            spline.control,
            lam,
            jnp.full(self.lam.shape, jnp.nan, dtype),
            jnp.array(False),
            lx.RESULTS.successful,
        )
        return state, objective(problem, spline.control, jnp.ones_like(spline.control), lam)

    def step(self, problem: Problem, state: HeldOutLeastSquaresState):
        exact = self._exact()
        lam, scores, normal = _selected(
            problem, self.lam, self.holdout, exact, state.control, self.early_stop
        )
        control, result = exact.solve_assembled(problem, normal, lam, state.control)
        energy = objective(problem, control, jnp.ones_like(control), lam)
        return HeldOutLeastSquaresState(control, lam, scores, jnp.array(True), result), energy

    def terminate(self, problem: Problem, state: HeldOutLeastSquaresState):
        exact_state = LeastSquaresState(
            state.control, jnp.ones_like(state.control), state.done, state.result
        )
        return self._exact().terminate(problem, exact_state)

    def to_spline(self, problem: Problem, state: HeldOutLeastSquaresState) -> ImplicitSpline:
        ones = jnp.ones_like(state.control)
        return ImplicitSpline(state.control, ones, problem.lower, problem.upper)
