"""The compiled solve of a fit, and how it is called: at top level with
[`jurs.COMPILER_OPTIONS`][] where they pay and through the store of exported fits, or
staged into a caller's jit, grad or vmap as it is."""

from __future__ import annotations

import equinox as eqx
import jax
import numpy as np
from jax.core import Tracer

from .._jit import FlatJit
from .._model.io import SPLINE_KEYS, check_spline_arrays
from .._model.spline import ImplicitSpline
from .._problem.validate import is_concrete
from ..solvers import AbstractSolver, solve
from ..solvers._base import run_first_try
from ..solvers._parts import solve_in_parts, solves_in_parts
from .compile import COMPILER_OPTIONS, call_stored
from .sharding import is_sharded


def check_start(shape, solver, init) -> None:
    """TypeError or ValueError unless ``solver`` is a jurs solver and ``init`` (if given) a
    finite spline on the grid ``shape``."""
    if not isinstance(solver, AbstractSolver):
        raise TypeError(f"solver must be a jurs solver, got {type(solver).__name__}")
    if init is not None and not isinstance(init, ImplicitSpline):
        raise TypeError(f"init must be a jurs.ImplicitSpline, got {type(init).__name__}")
    if init is not None and tuple(init.shape) != shape:
        raise ValueError(f"init spline has grid {init.shape}, expected {shape}")
    if init is not None and is_concrete(init):  # a NaN start ran into RESULTS.nonfinite
        check_spline_arrays({k: np.asarray(getattr(init, k)) for k in SPLINE_KEYS}, "init: ")


def _run(problem, solver, init, throw):
    return solve(solver, problem, init, throw=throw)


_solve = eqx.filter_jit(_run)


# The top-level plain compilation of a fit.
_solve_top_level = FlatJit(_run)
# The same compiled with COMPILER_OPTIONS, for large problems at top level (see fit).
# (filter_jit passes jax.jit's keywords on; its stub lists none of them.)
_solve_reassociating = eqx.filter_jit(_run, compiler_options=COMPILER_OPTIONS)  # pyright: ignore[reportCallIssue]


def _trace_state_clean() -> bool:
    """Whether no JAX transformation is tracing (JAX's own private test, where it has one;
    False leaves the answer to the public test below)."""
    try:
        from jax._src.core import trace_state_clean
    except ImportError:  # pragma: no cover - an older or newer JAX without it
        return False
    return bool(trace_state_clean())


def at_top_level(tree) -> bool:
    """Whether no leaf of ``tree`` is traced and a jit called here runs as an outermost
    computation, not staged into a caller's jit (XLA takes compiler options only there)."""
    if not is_concrete(tree):
        return False
    if _trace_state_clean():  # nothing is tracing: the common, cheap answer
        return True
    # JAX has no public "am I being staged out" check (jax-ml/jax#18544): a value made here
    # comes back as a tracer exactly when a jit, make_jaxpr, scan, cond, ... is tracing.
    # Under grad or vmap with no leaf of theirs in ``tree`` the jit runs on the concrete
    # arrays, outside them, where compiler options are taken (and ``throw`` is checked
    # on the host). A device_put compiles nothing.
    return not isinstance(jax.device_put(np.float32(0)), Tracer)


def _reassociation_pays(problem, solver) -> bool:
    """For solvers that declare themselves safe with [`jurs.COMPILER_OPTIONS`][]
    (``reassociation_safe``) on problems in the bucketed power form (the large ones, where
    the per-bucket sums are and where the options were measured to pay)."""
    local = problem.local
    return type(solver).reassociation_safe and local.terms is None and local.bucket_size > 1


def reassociates(problem, solver, init=None) -> bool:
    """Whether [`jurs.fit`][] compiles this solve with [`jurs.COMPILER_OPTIONS`][]:
    where they pay (``_reassociation_pays``), when called at top level."""
    return _reassociation_pays(problem, solver) and at_top_level((problem, solver, init))


def solve_fit(problem, solver, init, throw: bool):
    """``(solution, top_level)``: the compiled solve. At top level ``throw`` is left to the
    caller, who checks the verdict on the host once the host's own checks have judged it;
    under a transformation it is compiled in."""
    top_level = at_top_level((problem, solver, init))
    run = _solve_reassociating if top_level and _reassociation_pays(problem, solver) else _solve
    if not top_level:
        return run(problem, solver, init, throw), False
    # ``throw`` checked on the host after the call, not by a host callback inside it:
    # a compiled fit with a callback is never written to JAX's persistent compilation
    # cache, and without one a new process loads the fit instead of compiling it.
    # With jurs.enable_compilation_cache, the plain compilation also goes through the
    # store of exported fits: a new process skips its tracing too (call_stored).
    if is_sharded(problem):  # the store and the parts are one-device
        return _first_try_first(lambda s: run(problem, s, init, False), solver, problem), True
    if solves_in_parts(problem.num_points, problem.shape, solver, init):
        # Programs compiled per grid, not per number of points: a new cloud on a grid
        # seen before compiles nothing (jurs/solvers/_parts.py).
        solution = solve_in_parts(problem, solver, call_stored)
        if solution is not None:
            return solution, True
    if run is _solve_reassociating:
        return _first_try_first(lambda s: run(problem, s, init, False), solver, problem), True
    stored = lambda s: call_stored(_run, _solve_top_level, problem, s, init, False)  # noqa: E731
    return _first_try_first(stored, solver, problem), True


#: The verdict of a first try that broke down: its coefficients were not finite (the
#: driver keeps the last finite iterate and says ``nonfinite``), after which the solver
#: itself runs, its fallback with it. A first try that ``failed`` with finite coefficients
#: (a singular solve flagged by its amplification) is kept: the solver's own solve runs
#: the same first solve, and falls back only where C is not finite, so it would repeat it
#: to the same answer.
_RETRIED = ("nonfinite",)


def _first_try_first(compiled, solver, problem):
    """``compiled(solver)``, the solution of a top-level fit, by way of
    ``solver.first_try`` (``run_first_try``): retried with the solver itself where the
    first try's verdict says it broke down (``_RETRIED``)."""
    return run_first_try(compiled, solver, problem.shape, lambda sol: sol.status in _RETRIED)
