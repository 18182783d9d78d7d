"""Optimistix least-squares solvers and minimisers behind the jurs solver interface."""

from __future__ import annotations

from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
import optimistix as optx
from jax import Array

from .._model.spline import ImplicitSpline
from .._problem.energy import objective
from .._problem.problem import Problem
from .._problem.validate import check_nonnegative
from .._solution.solution import RESULTS
from . import _parameterisation as param
from ._base import AbstractSolver


class OptimistixState(eqx.Module):
    params: Any  # C, or (C, log w)
    done: Array  # bool: the optimistix solve has run
    result: optx.RESULTS  # optimistix's verdict
    num_steps: Array  # optimistix's step count


def map_result(result: optx.RESULTS) -> RESULTS:
    """Optimistix verdict -> jurs RESULTS: success and max_steps map to themselves, every
    other ending (a failed linear solve, divergence) to ``failed``. The optimistix verdict
    itself is kept in ``sol.state.result``."""
    return RESULTS.where(
        result == optx.RESULTS.successful,
        RESULTS.successful,
        RESULTS.where(
            result == optx.RESULTS.nonlinear_max_steps_reached,
            RESULTS.max_steps_reached,
            RESULTS.failed,
        ),
    )


class _AbstractOptimistix(AbstractSolver[OptimistixState]):
    """Shared machinery: one driver step runs the whole optimistix solve. Subclasses say
    which optimistix entry point runs (``_run``) and their default ``max_steps``."""

    solver: Any
    lam: Any
    joint: bool = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    warm_start: bool = eqx.field(static=True)
    adjoint: optx.AbstractAdjoint

    default_max_steps: ClassVar[int]  # each subclass sets its own

    def __init__(
        self,
        solver,
        *,
        lam=0.0,
        joint=False,
        max_steps=None,
        warm_start=True,
        adjoint=optx.ImplicitAdjoint(),
    ):
        self.solver, self.lam, self.joint = solver, lam, joint
        self.max_steps = self.default_max_steps if max_steps is None else max_steps
        self.warm_start, self.adjoint = warm_start, adjoint

    tol: ClassVar[float] = 0.0  # the optimistix solver's rtol/atol decide convergence

    def __check_init__(self):
        check_nonnegative("lam", self.lam)
        if int(self.max_steps) < 1:
            raise ValueError(f"max_steps must be >= 1, got {self.max_steps}")
        for name in ("rtol", "atol"):
            if hasattr(self.solver, name):
                check_nonnegative(f"solver.{name}", getattr(self.solver, name))

    def init(self, problem: Problem, spline: ImplicitSpline):
        y0 = param.initial_parameters(problem, spline, self.lam, self.joint, self.warm_start)
        control, weights = param.unpack(y0, self.joint)
        state = OptimistixState(y0, jnp.array(False), optx.RESULTS.successful, jnp.array(0))
        return state, objective(problem, control, weights, self.lam)

    def _run(self, problem: Problem, y0) -> optx.Solution:
        raise NotImplementedError

    def step(self, problem: Problem, state: OptimistixState):
        sol = self._run(problem, state.params)
        control, weights = param.unpack(sol.value, self.joint)
        energy = objective(problem, control, weights, self.lam)
        new_state = OptimistixState(sol.value, jnp.array(True), sol.result, sol.stats["num_steps"])
        return new_state, energy

    def terminate(self, problem: Problem, state: OptimistixState):
        return state.done, map_result(state.result)

    def to_spline(self, problem: Problem, state: OptimistixState) -> ImplicitSpline:
        return param.to_spline(problem, state.params, self.joint)


class OptimistixLeastSquares(_AbstractOptimistix):
    """Any optimistix least-squares solver on the residuals of ``E_d + lam R``.

    The residual vector is the 3m data residuals (eq. 16) and ``sqrt(2 lam)`` times every
    control difference of eq. 31 (``R = 2 sum_edges (C_a - C_b)^2``), over C alone
    (``joint=False``: a B-spline, w = 1) or over ``(C, log w)`` jointly (``joint=True``: a
    rational spline, weights positive by construction; see
    ``jurs.solvers._parameterisation`` for the scale gauge ``mean(log w) = 0``).

    Example::

        jurs.OptimistixLeastSquares(
            optx.LevenbergMarquardt(rtol=1e-8, atol=1e-10, linear_solver=lx.QR()),
            joint=True, max_steps=200)

    Args:
        solver: an ``optx.AbstractLeastSquaresSolver`` (LevenbergMarquardt, GaussNewton,
            Dogleg, ...) or an ``optx.AbstractMinimiser``; its ``rtol``/``atol`` decide
            convergence. The Jacobian is applied through ``jax.linearize`` of the local
            16-term evaluation: a dense solver (QR, the default) materialises it,
            ``lx.Normal(lx.CG(...))`` keeps it matrix-free.
        lam: the objective's lambda (``E = E_d + lam R``).
        joint: optimise the weights too.
        max_steps: passed to ``optx.least_squares`` (default 256; 1024 for
            [`OptimistixMinimiser`][jurs.OptimistixMinimiser]); the jurs driver runs one
            step that contains the whole optimistix solve (``sol.state.num_steps`` counts
            its steps, ``sol.state.result`` its verdict).
        warm_start: joint fits only: start from the exact best C for the start weights.
        adjoint: how gradients flow through the solve; the default implicit adjoint
            differentiates the optimality condition, not the iterations.
    """

    default_max_steps: ClassVar[int] = 256

    def _run(self, problem: Problem, y0) -> optx.Solution:
        return optx.least_squares(
            lambda y, args: param.residual_vector(y, args[0], args[1], self.joint),
            self.solver,
            y0,
            (problem, self.lam),
            max_steps=self.max_steps,
            adjoint=self.adjoint,
            throw=False,
        )


class OptimistixMinimiser(_AbstractOptimistix):
    """Any optimistix minimiser (BFGS, NonlinearCG, ``optx.OptaxMinimiser``, ...) on the
    scalar ``E_d + lam R`` (eq. 32), over C or jointly over ``(C, log w)``.

    Same arguments as [`OptimistixLeastSquares`][jurs.OptimistixLeastSquares];
    ``solver`` is an ``optx.AbstractMinimiser``. Example::

        jurs.OptimistixMinimiser(optx.BFGS(rtol=1e-10, atol=1e-12), lam=1e-4)
        jurs.OptimistixMinimiser(optx.OptaxMinimiser(optax.adam(1e-2), rtol=1e-8,
                                                     atol=1e-10), max_steps=5000)
    """

    default_max_steps: ClassVar[int] = 1024

    def _run(self, problem: Problem, y0) -> optx.Solution:
        return optx.minimise(
            lambda y, args: param.scalar_loss(y, args[0], args[1], self.joint),
            self.solver,
            y0,
            (problem, self.lam),
            max_steps=self.max_steps,
            adjoint=self.adjoint,
            throw=False,
        )
