"""jaxopt solvers (LBFGS, GaussNewton, LevenbergMarquardt) behind the jurs solver interface.

jaxopt is an optional extra (from the jurs checkout ``pip install -e '.[jaxopt]'``;
deprecated upstream): it is imported when a solve runs, so ``import jurs`` works without
it. jaxopt's LevenbergMarquardt rejects pytree parameters, so every wrapper optimises the
raveled vector of C (or of C and log w).
"""

from __future__ import annotations

from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
from jax import Array
from jax.flatten_util import ravel_pytree

from .._model.spline import ImplicitSpline
from .._problem.energy import objective
from .._problem.problem import Problem
from .._problem.validate import check_nonnegative
from .._solution.solution import RESULTS
from . import _parameterisation as param
from ._base import AbstractSolver


def _import_jaxopt():
    try:
        import warnings

        with warnings.catch_warnings():  # jaxopt warns about its own deprecation
            warnings.simplefilter("ignore", DeprecationWarning)
            import jaxopt
    except ImportError as exc:  # pragma: no cover - exercised only without jaxopt
        raise ImportError(
            "the jaxopt solvers need the optional dependency jaxopt: from the jurs checkout, "
            "pip install -e '.[jaxopt]'"
        ) from exc
    return jaxopt


class JaxoptState(eqx.Module):
    params: Any  # C, or (C, log w)
    done: Array  # bool: the jaxopt run has happened
    converged: Array  # bool: jaxopt's error <= tol
    num_steps: Array  # jaxopt's iteration count
    error: Array  # jaxopt's final error (gradient norm for these solvers)


class _AbstractJaxopt(AbstractSolver[JaxoptState]):
    """One driver step runs ``jaxopt.<Solver>(...).run`` on the raveled parameters.

    Fields: ``lam`` (objective lambda), ``joint`` (optimise log-weights too), ``max_steps``
    (jaxopt's ``maxiter``), ``tol`` (jaxopt's ``tol``: a gradient-norm threshold),
    ``warm_start`` (joint: start from the exact best C for the start weights) and
    ``options``, extra constructor arguments for the jaxopt solver as ``(name, value)``
    pairs. Gradients go through jaxopt's implicit differentiation.
    """

    lam: float = 0.0
    joint: bool = eqx.field(static=True, default=False)
    max_steps: int = eqx.field(static=True, default=500)
    tol: float = 1e-10
    warm_start: bool = eqx.field(static=True, default=True)
    options: tuple = eqx.field(static=True, default=())

    least_squares: ClassVar[bool]
    jaxopt_name: ClassVar[str]

    def __check_init__(self):
        check_nonnegative("lam", self.lam)
        check_nonnegative("tol", self.tol)
        if int(self.max_steps) < 1:
            raise ValueError(f"max_steps must be >= 1, got {self.max_steps}")

    def init(self, problem: Problem, spline: ImplicitSpline):
        y0 = param.initial_parameters(problem, spline, self.lam, self.joint, self.warm_start)
        control, weights = param.unpack(y0, self.joint)
        energy = objective(problem, control, weights, self.lam)
        false = jnp.array(False)
        state = JaxoptState(y0, false, false, jnp.array(0), jnp.asarray(jnp.inf, energy.dtype))
        return state, energy

    def step(self, problem: Problem, state: JaxoptState):
        jaxopt = _import_jaxopt()
        flat0, unravel = ravel_pytree(state.params)
        joint = self.joint
        if self.least_squares:

            def fun(x, problem, lam):
                return jnp.concatenate(
                    [r.ravel() for r in param.residual_vector(unravel(x), problem, lam, joint)]
                )

            kwargs = {"residual_fun": fun}
        else:

            def fun(x, problem, lam):
                return param.scalar_loss(unravel(x), problem, lam, joint)

            kwargs = {"fun": fun}
        solver = getattr(jaxopt, self.jaxopt_name)(
            **kwargs, maxiter=self.max_steps, tol=self.tol, **dict(self.options)
        )
        flat, info = solver.run(flat0, problem, self.lam)
        params = unravel(flat)
        control, weights = param.unpack(params, joint)
        energy = objective(problem, control, weights, self.lam)
        new = JaxoptState(
            params, jnp.array(True), info.error <= self.tol, info.iter_num, info.error
        )
        return new, energy

    def terminate(self, problem: Problem, state: JaxoptState):
        result = RESULTS.where(
            state.converged | ~state.done, RESULTS.successful, RESULTS.max_steps_reached
        )
        return state.done, result

    def to_spline(self, problem: Problem, state: JaxoptState) -> ImplicitSpline:
        return param.to_spline(problem, state.params, self.joint)


class JaxoptLBFGS(_AbstractJaxopt):
    """``jaxopt.LBFGS`` on the scalar ``E_d + lam R`` (eq. 32), over C or (C, log w).
    See ``_AbstractJaxopt`` for the fields."""

    least_squares: ClassVar[bool] = False
    jaxopt_name: ClassVar[str] = "LBFGS"


class JaxoptGaussNewton(_AbstractJaxopt):
    """``jaxopt.GaussNewton`` on the residuals of ``E_d + lam R`` (data residuals and
    ``sqrt(2 lam)`` control differences), over C or (C, log w)."""

    least_squares: ClassVar[bool] = True
    jaxopt_name: ClassVar[str] = "GaussNewton"


class JaxoptLevenbergMarquardt(_AbstractJaxopt):
    """``jaxopt.LevenbergMarquardt`` on the residuals of ``E_d + lam R``, over C or
    (C, log w). Pass e.g. ``options=(("solver", "cholesky"),)`` to pick its linear solver
    (jaxopt's default is CG on the normal equations)."""

    least_squares: ClassVar[bool] = True
    jaxopt_name: ClassVar[str] = "LevenbergMarquardt"
