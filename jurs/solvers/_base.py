"""The interface every jurs solver implements."""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import Any, ClassVar, Generic, TypeVar

import equinox as eqx
import jax.numpy as jnp
from jax import Array

from .._model.spline import ImplicitSpline
from .._problem.problem import Problem
from .._solution.solution import RESULTS

State = TypeVar("State")


class AbstractSolver(eqx.Module, Generic[State]):
    """An immutable solver: hyperparameters as fields, the iterate in an explicit state.

    The driver ([`jurs.solve`][]) owns the loop: it calls
    [`init`][jurs.AbstractSolver.init] once, then [`step`][jurs.AbstractSolver.step]
    until ``|E_new - E_old| < tol`` (eq. 38),
    [`terminate`][jurs.AbstractSolver.terminate] says so, the energy stops being finite,
    or ``max_steps`` steps have run.

    Subclasses define the fields ``max_steps`` (static int), ``tol`` and ``lam`` (the
    lambda that the reported energy ``E = E_d + lam R`` uses).
    """

    max_steps: eqx.AbstractVar[int]
    tol: eqx.AbstractVar[Any]
    lam: eqx.AbstractVar[Any]

    #: Whether [`jurs.fit`][] may compile this solver with [`jurs.COMPILER_OPTIONS`][]
    #: (floating-point reassociation) on large problems. True only for solvers measured to
    #: move at rounding level with them (``benchmarks/results/solvers.md``); an outside
    #: optimiser that wanders near its minimum can end elsewhere (see ``jurs._fit.compile``).
    reassociation_safe: ClassVar[bool] = False
    #: Whether the solver works sample by sample and holds a few grids, never the
    #: normal equations' stencil (its memory estimate, ``jurs._problem.problem.fit_memory``).
    per_sample_iterations: ClassVar[bool] = False
    #: Whether the solver expects outliers in its data: a fit by it with every setting
    #: given is still judged by its closed components away from the data, such as loops
    #: around outliers it did not weigh down (``jurs._solution.verdicts.check_components``).
    expects_outliers: ClassVar[bool] = False
    #: Whether the solver chooses its lambda among candidates during the fit (``lam`` an
    #: array; ``fitted_lam`` reports the choice).
    chooses_lam: ClassVar[bool] = False

    @abc.abstractmethod
    def init(self, problem: Problem, spline: ImplicitSpline) -> tuple[State, Array]:
        """Initial state from a starting spline; returns ``(state, energy)``."""

    @abc.abstractmethod
    def step(self, problem: Problem, state: State) -> tuple[State, Array]:
        """One iteration; returns ``(new_state, energy)``."""

    @abc.abstractmethod
    def to_spline(self, problem: Problem, state: State) -> ImplicitSpline:
        """The spline a state stands for."""

    def fitted_lam(self, state: State) -> Any:
        """The lambda of the fit in ``state``, which ``sol.metrics`` report: ``lam``, except
        for a solver that chooses it among candidates."""
        return self.lam

    def first_try(self, shape: tuple[int, ...]) -> AbstractSolver:
        """The solver a top-level fit on the grid ``shape`` runs first: ``self``, or for a
        solver that falls back to another linear solve only where its first one breaks
        down ([`jurs.LeastSquares`][]) that first solve alone, so that the fallback is
        compiled only where one is needed. A fit whose first try's coefficients are not
        finite runs ``self``."""
        del shape
        return self

    def judged_problem(self, problem: Problem, state: State) -> Problem:
        """The problem whose points the verdicts on the fit read (the offset-sign check):
        ``problem``, except for a solver that sets points aside in ``state``."""
        del state
        return problem

    def terminate(self, problem: Problem, state: State) -> tuple[Array, RESULTS]:
        """Solver-specific stop (e.g. a direct solve is done after one step)."""
        return jnp.array(False), RESULTS.successful


Result = TypeVar("Result")


def run_first_try(
    run: Callable[[AbstractSolver], Result],
    solver: AbstractSolver,
    shape: tuple[int, ...],
    broke_down: Callable[[Result], bool],
) -> Result:
    """``run(solver)`` by way of ``solver.first_try(shape)``: ``run`` of the first try, and
    ``run(solver)`` (its fallback compiled only then) where ``broke_down`` says of that
    result that the first try may have broken down; a single run where the first try is
    the solver itself. For top-level callers, whose solver is concrete."""
    # Through the class: equinox wraps a method read off a Module in a new Module, a cost
    # that a warm small fit notices.
    first = type(solver).first_try(solver, shape)
    result = run(first)
    if first is solver or not broke_down(result):
        return result
    return run(solver)
