"""RobustLeastSquares: outlier-robust fits by iteratively reweighted exact solves."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jax import Array

from .._linalg.normal import DEFAULT_CHUNK
from .._model.spline import ImplicitSpline
from .._problem.energy import bspline_residuals, regulariser
from .._problem.problem import Problem
from .._problem.validate import check_count, check_nonnegative, is_concrete
from ._base import AbstractSolver
from ._least_squares import DEFAULT_RIDGE, LeastSquares, LeastSquaresState

#: Tuning constants c of the losses (residuals in units of the scale s): the usual 95 %
#: asymptotic efficiency at Gaussian noise of each M-estimator.
TUNING = {"huber": 1.345, "cauchy": 2.385, "tukey": 4.685}

#: 1 / Phi^-1(3/4): the median absolute deviation of a standard normal is 1 / 1.4826.
MAD_TO_SIGMA = 1.4826

#: Smallest automatic scale, relative to eps. A fit to clean data leaves residuals far below
#: eps (approximation error); without a floor their median would be the unit, and a
#: Cauchy or Tukey loss would then set aside the points of the most curved parts.
SCALE_FLOOR = 0.02


#: Weight below which a point counts as set aside (the docs' rule): the offset-sign
#: verdict does not read such points, whose offsets the fit no longer follows.
SET_ASIDE_WEIGHT = 0.1


def _check_scale_range(scale) -> None:
    """ValueError where a given ``scale`` squared (the unit of ``E_rob``) leaves the range
    of the float type (with four decades to spare): at 1e300 the energy overflowed, at
    1e-300 every weight fell to 0, and the fit ended ``nonfinite`` with nothing naming the
    scale. Traced scales pass unchecked."""
    if not is_concrete(scale):
        return
    info = jnp.finfo(jnp.result_type(float))
    low, high = 1e4 * float(np.sqrt(info.tiny)), 1e-4 * float(np.sqrt(info.max))
    if not low <= float(scale) <= high:
        raise ValueError(
            f"scale = {float(scale):.3g} is outside [{low:.3g}, {high:.3g}]: its square, the "
            f"unit of the robust energy, leaves the range of {info.dtype.name}. The scale "
            "is the size of an inlier's residual, about the offset eps or below; leave it "
            "None to estimate it from the fit"
        )


def robust_weight(loss: str, t: Array) -> Array:
    """IRLS weight ``w(t) = rho'(t) / (2 t)`` of the loss at residuals ``t`` (in units of s)."""
    c = TUNING[loss]
    if loss == "huber":
        return jnp.minimum(1.0, c / jnp.maximum(jnp.abs(t), 1e-300))
    if loss == "cauchy":
        return 1.0 / (1.0 + (t / c) ** 2)
    return jnp.where(jnp.abs(t) < c, (1.0 - (t / c) ** 2) ** 2, 0.0)  # tukey


def robust_loss(loss: str, t: Array) -> Array:
    """``rho(t)``, scaled so that ``rho(t) = t^2`` near 0 (the least-squares term)."""
    c = TUNING[loss]
    if loss == "huber":
        a = jnp.abs(t)
        return jnp.where(a <= c, t * t, 2.0 * c * a - c * c)
    if loss == "cauchy":
        return c * c * jnp.log1p((t / c) ** 2)
    u = jnp.minimum((t / c) ** 2, 1.0)  # tukey
    return c * c / 3.0 * (1.0 - (1.0 - u) ** 3)


def slot_points(problem: Problem) -> Array:
    """The point of every slot: slots index the paper's order [P, P + d n, P - d n]."""
    return problem.sample_index % problem.num_points


class RobustLeastSquaresState(eqx.Module):
    control: Array  # C
    point_weights: Array  # (m,) robust weight of each point, for the fit in ``control``
    scale: Array  # s the weights were computed with
    result: lx.RESULTS  # the last linear solve's verdict
    energy: Array  # E_rob of the fit in ``control``
    settled: Array  # bool: E_rob changed by at most rtol |E_rob| in the last step
    solved: Array  # bool: ``control`` is a solve's (not the start)


class RobustLeastSquares(AbstractSolver[RobustLeastSquaresState]):
    """Outlier-robust fit: iteratively reweighted least squares (IRLS) with a robust loss.

    Minimises ``E_rob(C) = s^2 sum_i rho(e_i / s) + lam R(C)`` over the B-spline
    coefficients (w = 1), where ``e_i = sqrt(r_P^2 + r_+^2 + r_-^2)`` is the residual of
    point i over its three samples (eq. 4-5: the point and its two offset samples are
    one group, so an outlier takes its offsets with it) and ``rho`` is, with ``t = e / s``
    and the tuning constant ``c``:

    * ``"huber"`` (c = 1.345): ``t^2`` for ``|t| <= c``, ``2 c |t| - c^2`` beyond;
      weight ``min(1, c / |t|)``. Down-weights, never sets aside.
    * ``"cauchy"`` (c = 2.385): ``c^2 log(1 + t^2 / c^2)``; weight ``1 / (1 + t^2 / c^2)``.
    * ``"tukey"`` (biweight, c = 4.685): ``c^2 / 3 (1 - (1 - t^2 / c^2)^3)`` for
      ``|t| < c``, ``c^2 / 3`` beyond; weight ``(1 - t^2 / c^2)^2``, 0 beyond c.

    ``rho(t) = t^2`` near 0, so on clean data ``E_rob`` is ``E_d + lam R``. Each driver step
    is one exact weighted solve ([`LeastSquares`][jurs.LeastSquares]) with the weights
    ``w_i = rho'(t_i) / (2 t_i)`` of the previous fit: each sample's row enters ``D^T D``
    and ``D^T b`` multiplied by its point's ``w_i``, i.e. the solve minimises
    ``sum_k w_k r_k^2 + lam R``. The weights are passed as the problem's float ``mask``,
    which the B-spline assembly ([`jurs.internal.normal_equations`][] with w = 1) takes
    linearly (``sum_k mask_k B_k B_k^T``, ``sum_k mask_k b_k B_k``); the first step has all
    weights 1 (the plain least-squares fit). The energy reported to the driver is
    ``E_rob`` at the new fit, so ``tol`` (absolute, as every solver's) stops the loop
    once the reweighting has settled. Each solve after the first starts from the last
    fit (a surface's then skips the coarse grid's fit that supplies a cold
    start's far field: [`LeastSquares.minimise`][jurs.LeastSquares.minimise]).

    The final weights are ``sol.state.point_weights``, one per point of the problem in its
    point order, computed from the final fit (those of its last solve, once converged),
    0 for padding. [`jurs.fit`][] pads a cloud with masked copies after the caller's
    points: ``sol.state.point_weights[:len(points)]`` are the caller's. Weights near 0
    mark the points set aside (Tukey: exactly 0 beyond ``c s``; Cauchy: below 0.1 beyond
    ``3 c s``); Huber's stay above ``c s / e_i``. The offset-sign verdict
    (``inconsistent_normals``) reads only the points of weight ``SET_ASIDE_WEIGHT`` (0.1)
    and above.

    Args:
        lam: the objective's lambda, as [`LeastSquares`][jurs.LeastSquares].
        loss: ``"huber"``, ``"cauchy"`` or ``"tukey"``.
        scale: the residual scale s; None (default) estimates it at every step from the
            current fit: ``1.4826 median_i e_i`` over the real points (robust to up to
            half of them being outliers), at least ``SCALE_FLOOR`` eps (clean data
            leave residuals far below eps, where a tiny unit would set curved parts aside),
            and never above the previous step's: with as many outliers as inliers the
            median is the smallest outlier's residual, which grew as the fit followed it,
            and the rising scale raised ``E_rob`` step after step (a Tukey fit oscillated
            to ``max_steps``); non-increasing, it makes every step a descent. (Fixed at
            the plain fit's, it stayed too large there to release the outliers.)
        max_steps: reweighted solves at most (the first is the plain fit). A Cauchy fit
            of Example 1 with 3 % planted outliers converges in 50 (25 with a scale free
            to rise); with as many outliers
            as inliers they are released a few at a time, in 20-90 steps (a circle, 100
            points and 100 outliers, 20 x 20 to 31 x 31). Not more by default: on clean
            shapes with sharp corners a hard loss sets corner points aside step after
            step (Tukey on glyph B: 5.8 % below weight 0.1 after 30 steps, 7.5 % after 60,
            10 % after 100; docs/robustness.md).
        tol: stop when ``E_rob`` changes by less than this (absolute) between steps.
        rtol: stop, too, when it changes by at most ``rtol |E_rob|`` (0: off).
        linear_solver, chunk_size, ridge: as [`LeastSquares`][jurs.LeastSquares].

    Curves and surfaces; polynomial B-splines only (a float mask is a row weight only in
    the B-spline assembly). Hard losses (Tukey, Cauchy) are not convex: the fit is a local
    minimum reached from the plain one, and can set aside inliers where the plain fit is
    far off (a badly wrong start); Huber is convex.
    """

    lam: float = 0.0
    loss: str = eqx.field(static=True, default="cauchy")
    scale: float | None = None
    max_steps: int = eqx.field(static=True, default=60)
    tol: float = 1e-10
    rtol: float = 0.0
    linear_solver: lx.AbstractLinearSolver | None = None
    chunk_size: int = eqx.field(static=True, default=DEFAULT_CHUNK)
    ridge: float = DEFAULT_RIDGE

    # Not measured under reassociation: a hard loss's cut can turn rounding into a weight.
    reassociation_safe: ClassVar[bool] = False
    expects_outliers: ClassVar[bool] = True

    def __check_init__(self):
        if self.loss not in TUNING:
            raise ValueError(f"loss must be one of {sorted(TUNING)}, got {self.loss!r}")
        check_nonnegative("lam", self.lam)
        check_nonnegative("tol", self.tol)
        check_nonnegative("rtol", self.rtol)
        check_count("max_steps", self.max_steps, 1)
        if self.scale is not None:
            check_nonnegative("scale", self.scale, strict=True)
            _check_scale_range(self.scale)
        # The exact solve checks its own fields (ridge, chunk_size, linear_solver).
        self._exact()

    def _exact(self) -> LeastSquares:
        return LeastSquares(
            lam=self.lam,
            linear_solver=self.linear_solver,
            chunk_size=self.chunk_size,
            ridge=self.ridge,
        )

    def _point_residuals(self, problem: Problem, control: Array) -> tuple[Array, Array]:
        """``(e, real)``: ``e_i`` (m,) and whether point i is a real (not padding) point."""
        m = problem.num_points
        point = slot_points(problem)
        r = bspline_residuals(problem, control)  # 0 at padding
        e2 = jax.ops.segment_sum(r * r, point, num_segments=m)
        real = jax.ops.segment_sum(problem.is_data, point, num_segments=m) > 0
        return jnp.sqrt(e2), real

    def _reweigh(self, problem: Problem, control: Array, previous: Array | None = None):
        """``(weights, scale, E_rob)`` of the fit in ``control``; an estimated scale never
        exceeds the ``previous`` one."""
        e, real = self._point_residuals(problem, control)
        return self.reweigh(e, real, problem.eps, regulariser(control), previous)

    def reweigh(
        self, e: Array, real: Array, eps, regularisation, previous: Array | None = None
    ) -> tuple[Array, Array, Array]:
        """``(weights, scale, E_rob)`` from the points' residuals ``e`` (m,) (``real``: the
        points that are not padding) and ``R`` of the fit, whatever its basis: the IRLS
        weights ``rho'(t) / (2 t)`` at ``t = e / s``, the scale ``s`` (given, or
        ``1.4826 median e``, at least ``SCALE_FLOOR eps``, at most the ``previous``), and
        the energy ``s^2 sum rho(t) + lam R``."""
        if self.scale is None:
            median = jnp.nanmedian(jnp.where(real, e, jnp.nan))
            scale = jnp.maximum(MAD_TO_SIGMA * median, SCALE_FLOOR * eps)
            if previous is not None:
                scale = jnp.minimum(scale, previous)
        else:
            scale = jnp.asarray(self.scale, e.dtype)
        scale = jax.lax.stop_gradient(scale)  # a unit, not a variable
        t = e / scale
        weights = jnp.where(real, robust_weight(self.loss, t), 0.0)
        rho = jnp.sum(jnp.where(real, robust_loss(self.loss, t), 0.0))
        energy = scale * scale * rho + self.lam * regularisation
        return weights, scale, energy

    def init(self, problem: Problem, spline: ImplicitSpline):
        _, scale, energy = self._reweigh(problem, spline.control)
        # The first solve is the plain fit: the start (C = 0 by default) says nothing
        # about which points are outliers.
        weights = jnp.ones(problem.num_points, spline.control.dtype)
        state = RobustLeastSquaresState(
            spline.control,
            weights,
            scale,
            lx.RESULTS.successful,
            energy,
            jnp.array(False),
            jnp.array(False),
        )
        return state, energy

    @staticmethod
    def _exact_state(state: RobustLeastSquaresState, result) -> LeastSquaresState:
        """The LeastSquares state at ``state``'s fit (w = 1, not yet solved)."""
        return LeastSquaresState(
            state.control, jnp.ones_like(state.control), jnp.array(False), result
        )

    def step(self, problem: Problem, state: RobustLeastSquaresState):
        slot_weights = state.point_weights[slot_points(problem)]
        weighted = eqx.tree_at(lambda p: p.mask, problem, problem.mask * slot_weights)
        # After the first solve, each starts from the last: its far field is that of a
        # problem reweighted only a little, and a surface skips the cascade. The weighted
        # E_d + lam R is not computed: E_rob is this solver's energy.
        warm = state.solved
        control, result = self._exact().minimise(
            weighted, jnp.ones_like(state.control), state.control, warm
        )
        weights, scale, energy = self._reweigh(problem, control, state.scale)
        settled = jnp.abs(energy - state.energy) <= self.rtol * jnp.abs(energy)
        new = RobustLeastSquaresState(
            control, weights, scale, result, energy, settled, jnp.array(True)
        )
        return new, energy

    def terminate(self, problem: Problem, state: RobustLeastSquaresState):
        _, result = self._exact().terminate(problem, self._exact_state(state, state.result))
        # The driver's energy test (tol) stops the loop too.
        return state.settled & (self.rtol > 0), result

    def judged_problem(self, problem: Problem, state: RobustLeastSquaresState) -> Problem:
        """``problem`` without the points set aside (weight below ``SET_ASIDE_WEIGHT``):
        with half the points outliers, the far field of a Tukey fit read the offsets of a
        quarter of them the wrong way round, and the fit was ``inconsistent_normals``."""
        kept = state.point_weights[slot_points(problem)] >= SET_ASIDE_WEIGHT
        return eqx.tree_at(lambda p: p.mask, problem, jnp.where(kept, problem.mask, 0.0))

    def to_spline(self, problem: Problem, state: RobustLeastSquaresState) -> ImplicitSpline:
        ones = jnp.ones_like(state.control)
        return ImplicitSpline(state.control, ones, problem.lower, problem.upper)
