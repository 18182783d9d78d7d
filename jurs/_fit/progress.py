"""Running an iterative fit in chunks of steps: progress reports and iteration snapshots.

``jurs.fit`` runs a whole solve in one compiled loop. To report progress, or to look at the
iterate after given step counts (the paper's Fig. 15), ``solve_in_chunks`` drives the
solver driver's pieces (``jurs.solvers._driver.start``, ``advance`` and ``finish``) on
one problem, a chunk of steps per call, carrying the solver's state from chunk to chunk:
the chunked run follows the same iterates as one [`jurs.solve`][] (to rounding; the tests
check this). ``chunked_run`` is that solve as a step of [`jurs.fit`][]'s flow, which
[`fit_in_chunks`][jurs.fit_in_chunks] (``fit.py``) and the progress callback of ``jurs.fit``
run. Solvers other than I-PIA and IURS are run in one call.
"""

from __future__ import annotations

from typing import Any, Callable, cast

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._model.spline import ImplicitSpline
from .._problem.problem import Problem
from .._solution.solution import (
    Solution,
    raise_unless_reconstruction,
)
from ..solvers import IPIA, IURS, AbstractSolver, solve
from ..solvers._driver import Carry, advance, finish, start
from .call import reassociates
from .compile import COMPILER_OPTIONS, call_stored
from .sharding import is_sharded

#: Solvers run in chunks; the others run in one call (one or a few exact solves).
CHUNKABLE = (IPIA, IURS)


def chunk_size(steps: int, target_chunks: int = 25) -> int:
    """A divisor of ``steps`` near ``steps / target_chunks`` (equal chunks);
    ``steps`` itself when none is reasonably close."""
    if steps <= target_chunks:
        return max(steps, 1)
    ideal = steps / target_chunks
    divisors = [c for c in range(1, steps + 1) if steps % c == 0 and ideal / 4 <= c <= ideal * 4]
    return min(divisors, key=lambda c: abs(np.log(c / ideal))) if divisors else steps


# The pieces as functions of (problem, solver, ...), jit-compiled once each: a chunk's step
# count is traced (``_advance``'s ``num_steps``), so chunks cut short by a checkpoint or by
# max_steps reuse the compiled chunk. Every piece runs without a host callback (throw is
# checked on the host), so JAX's persistent cache and the store of exported fits
# (``jurs._fit.compile.call_stored``) keep them.
def _start(problem: Problem, solver: AbstractSolver, spline: ImplicitSpline | None) -> Carry:
    return start(solver, problem, spline)


def _advance(problem: Problem, solver: AbstractSolver, carry: Carry, num_steps, bound: int):
    return advance(solver, problem, carry, num_steps, bound=bound)


def _finish(problem: Problem, solver: AbstractSolver, carry: Carry) -> Solution:
    return finish(solver, problem, carry, throw=False)


def _whole(problem: Problem, solver: AbstractSolver, spline: ImplicitSpline | None) -> Solution:
    return solve(solver, problem, spline, throw=False)


def _jit(fn: Callable[..., Any], **options) -> Callable[..., Any]:
    # (filter_jit passes jax.jit's keywords on; its stub lists none of them.)
    return eqx.filter_jit(fn, **options)  # pyright: ignore[reportCallIssue]


_PIECES = (_start, _advance, _finish, _whole)
_JITTED = {fn: _jit(fn) for fn in _PIECES}
# The same compiled with COMPILER_OPTIONS, for large problems (as jurs.fit compiles them).
_REASSOCIATING = {fn: _jit(fn, compiler_options=COMPILER_OPTIONS) for fn in _PIECES}


def _call(fn: Callable[..., Any], reassociate: bool, problem: Problem, *args) -> Any:
    """``fn(problem, *args)`` compiled as [`jurs.fit`][] compiles its solve: with
    [`jurs.COMPILER_OPTIONS`][] where they pay, else through the store of exported
    fits (one-device problems)."""
    if reassociate:
        return _REASSOCIATING[fn](problem, *args)
    if is_sharded(problem):  # the store is one-device
        return _JITTED[fn](problem, *args)
    return call_stored(fn, _JITTED[fn], problem, *args)


def _checked_checkpoints(checkpoints, total: int) -> list[int]:
    checkpoints = sorted({int(c) for c in checkpoints})
    if any(c < 0 or c > total for c in checkpoints):
        raise ValueError(f"checkpoints must lie in [0, max_steps = {total}], got {checkpoints}")
    return checkpoints


def solve_in_chunks(
    solver: AbstractSolver,
    problem: Problem,
    init: ImplicitSpline | None = None,
    *,
    chunk: int | None = None,
    checkpoints=(),
    callback: Callable[[int, int], None] | None = None,
    throw: bool = True,
) -> tuple[Solution, dict[int, ImplicitSpline]]:
    """[`jurs.solve`][] of ``problem`` by ``solver`` from ``init``, run ``chunk`` steps
    per call, with a report after each call and the iterate kept at given step counts.

    The solver's state is carried from chunk to chunk as it is, so the run takes the
    steps of one [`jurs.solve`][], stops by the same rules and returns the same
    Solution, to rounding: ``num_steps``, the whole ``energy_history`` (``max_steps + 1``
    entries, NaN past the end), the verdict and the metrics. The run compiles three
    functions, each once: its start, a chunk (the step count traced: chunks cut short by
    a checkpoint or by ``max_steps`` reuse it) and its end. Solvers other than I-PIA and
    IURS (one or a few exact solves) are run in one compiled call.

    On the host, with concrete arguments: not traceable (use [`jurs.solve`][] under
    ``jit``, ``grad`` or ``vmap``).

    Args:
        solver: the solver; its ``max_steps`` is the total number of steps.
        problem: from [`jurs.make_problem`][].
        init: the starting spline; default C = 0, w = 1.
        chunk: steps per call at most (default ``chunk_size``). A chunk also ends at
            each checkpoint.
        checkpoints: step counts at which to keep the spline (e.g. ``(0, 10, 50, 200)``),
            within ``[0, max_steps]``; for a solver run in one call only ``max_steps``.
        callback: called as ``callback(steps_done, max_steps)`` after every chunk.
        throw: raise ``equinox.EquinoxRuntimeError`` on the run's final verdict where
            [`jurs.solve`][] would (checked on the host once the run has ended).

    Returns:
        ``(solution, snapshots)``: the [`jurs.Solution`][] and a dict ``{step: spline}``
        for the checkpoints reached (a run that converges early stops there).
    """
    total = int(solver.max_steps)
    checkpoints = _checked_checkpoints(checkpoints, total)
    reassociate = reassociates(problem, solver, init)
    if not isinstance(solver, CHUNKABLE):
        if any(c != total for c in checkpoints):
            raise ValueError(
                f"{type(solver).__name__} runs in one call: the only checkpoint "
                f"it can give is max_steps = {total}"
            )
        sol: Solution = _call(_whole, reassociate, problem, solver, init)
        if callback:
            callback(total, total)
        # A uniform problem's solve: its spline is an ImplicitSpline.
        snapshots = {c: cast(ImplicitSpline, sol.spline) for c in checkpoints}
    else:
        chunk = max(1, min(chunk_size(total) if chunk is None else int(chunk), total))
        carry = _call(_start, reassociate, problem, solver, init)
        snapshots = {}
        if 0 in checkpoints:
            snapshots[0] = solver.to_spline(problem, carry.state)
        done, stopped = 0, bool(carry.stopped)
        while done < total and not stopped:
            goal = min([done + chunk] + [c for c in checkpoints if c > done])
            steps = jnp.asarray(goal - done, dtype=carry.step.dtype)
            carry = _call(_advance, reassociate, problem, solver, carry, steps, chunk)
            done, stopped = int(carry.step), bool(carry.stopped)
            if done in checkpoints:
                snapshots[done] = solver.to_spline(problem, carry.state)
            if callback:
                callback(done, total)
        sol = _call(_finish, reassociate, problem, solver, carry)
    raise_unless_reconstruction(sol, throw)
    return sol, snapshots


def chunked_run(problem, solver, init, throw, **options):
    """The solve of [`jurs.fit`][]'s flow by ``solve_in_chunks`` (``options``: its
    keywords), always at top level; the verdict is raised by the fit, after its checks:
    ``(solution, True, snapshots)``."""
    del throw
    sol, snapshots = solve_in_chunks(solver, problem, init, throw=False, **options)
    return sol, True, snapshots
