"""The one loop every solver runs in.

[`solve`][jurs.solve] runs it whole. It is composed of three pieces that a caller who
wants to stop between steps reuses (``jurs._fit.progress.solve_in_chunks``, the progress
bar's chunked run): ``start`` (the solver's ``init``, the energy and the history buffer),
``advance`` (at most a given number of further steps, under the same stop rules) and
``finish`` (the verdict, the metrics, the offset-sign check and ``throw``). Run in
pieces, the state is carried exactly, so the pieces follow the same iterates as one
[`solve`][jurs.solve].
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
from jax import Array

from .._jit import as_arrays
from .._model.precision import full_precision
from .._model.spline import ImplicitSpline
from .._problem.energy import metrics as compute_metrics
from .._problem.problem import Problem
from .._solution.solution import RAISED_RESULTS, RESULTS, Solution, error_message, unusable
from .._solution.verdicts import MAX_OFFSET_SIGN_DISAGREEMENT, offset_sign_disagreement
from ._base import AbstractSolver


class Carry(eqx.Module):
    """Where a run stands between ``start``, ``advance`` and ``finish``.

    Attributes:
        step: steps taken so far.
        state: the solver's state after them (the last finite iterate).
        energy: its energy (the last finite one).
        nonfinite: whether the last step's energy was NaN/Inf (or the start's).
        history: ``solver.max_steps + 1`` energies, NaN past ``step``.
        stopped: whether a stop rule other than ``max_steps`` was met (tol, the
            solver's ``terminate``, a non-finite energy): no further step runs.
    """

    step: Array
    state: Any
    energy: Array
    nonfinite: Array
    history: Array
    stopped: Array


@full_precision
def start(solver: AbstractSolver, problem: Problem, spline: ImplicitSpline | None = None) -> Carry:
    """The run of ``solver`` on ``problem`` before its first step, from ``spline``
    (default: C = 0, w = 1, as Algorithm 1): the solver's ``init``, its energy as the
    history's first entry, and the solver's own stop rule read on it. Traceable."""
    if spline is None:
        dtype = problem.samples.dtype
        spline = ImplicitSpline(
            jnp.zeros(problem.shape, dtype),
            jnp.ones(problem.shape, dtype),
            problem.lower,
            problem.upper,
        )
    state, energy = solver.init(problem, spline)
    history = jnp.full((solver.max_steps + 1,), jnp.nan, dtype=energy.dtype).at[0].set(energy)
    done, _ = solver.terminate(problem, state)
    return Carry(
        step=jnp.array(0),
        state=state,
        energy=energy,
        nonfinite=~jnp.isfinite(energy),
        history=history,
        stopped=done | ~jnp.isfinite(energy),
    )


@full_precision
def advance(
    solver: AbstractSolver,
    problem: Problem,
    carry: Carry,
    num_steps: int | Array,
    *,
    bound: int | None = None,
) -> Carry:
    """``carry`` after at most ``num_steps`` more steps: fewer where the run reaches
    ``solver.max_steps`` or stops (``|E_new - E_old| < solver.tol``, eq. 38; the solver's
    ``terminate``; a NaN/Inf energy, whose step is not accepted). A stopped ``carry``
    is returned as it is. Traceable.

    ``num_steps`` may be traced (one compiled chunk for every count); the loop is then
    compiled for at most ``bound`` steps (a static int, default ``num_steps`` where that
    is an int, else ``solver.max_steps``), and ``num_steps`` must not exceed it."""
    max_steps = solver.max_steps
    if bound is None:
        bound = num_steps if isinstance(num_steps, int) else max_steps
    end = jnp.minimum(carry.step + num_steps, max_steps)

    def cond(carry: Carry):
        return (carry.step < end) & ~carry.stopped

    def body(carry: Carry):
        k, state, energy = carry.step, carry.state, carry.energy
        new_state, new_energy = solver.step(problem, state)
        finite = jnp.isfinite(new_energy)
        # Keep the last finite iterate so a diverging run loses nothing.
        state = jax.tree_util.tree_map(
            lambda new, old: jnp.where(finite, new, old), new_state, state
        )
        converged = jnp.abs(new_energy - energy) < solver.tol
        stop_now, _ = solver.terminate(problem, state)
        return Carry(
            step=k + 1,
            state=state,
            energy=jnp.where(finite, new_energy, energy),
            nonfinite=~finite,
            history=carry.history.at[k + 1].set(new_energy),
            stopped=~finite | converged | stop_now,
        )

    # A checkpointed loop runs as a plain while loop forward and, unlike lax.while_loop,
    # can be reverse-differentiated (jax.grad of a loss of the fit), with O(log) memory.
    # The history buffer is written in place.
    return eqxi.while_loop(
        cond,
        body,
        carry,
        max_steps=max(min(bound, max_steps), 1),
        kind="checkpointed",
        buffers=lambda c: c.history,
    )


@full_precision
def finish(solver: AbstractSolver, problem: Problem, carry: Carry, throw: bool = True) -> Solution:
    """The [`jurs.Solution`][] of a run that has reached ``carry``: its verdict, its
    metrics and the offset-sign check of [`solve`][jurs.solve] (which see for
    ``throw``). Traceable."""
    state = carry.state
    _, solver_result = solver.terminate(problem, state)
    fitted = solver.to_spline(problem, state)
    lam = solver.fitted_lam(state)
    metrics = compute_metrics(problem, fitted, lam)
    # (Points a robust solver set aside are not read: their offsets are not fitted.)
    disagreement = offset_sign_disagreement(solver.judged_problem(problem, state), fitted)
    return concluded(carry, solver_result, fitted, lam, metrics, disagreement, throw)


def concluded(
    carry: Carry,
    solver_result: RESULTS,
    fitted: ImplicitSpline,
    lam,
    metrics: dict[str, Array],
    disagreement: Array,
    throw: bool = True,
) -> Solution:
    """The [`jurs.Solution`][] of a run that reached ``carry``, from the solver's own
    verdict on its state (``solver_result``), its spline, lambda, metrics and
    offset-sign disagreement, however they were computed (``finish``, or from a cloud
    taken in parts: ``jurs._fit.call``). Traceable."""
    # The solver's own verdict on its state, when it is not success, stands whether or not
    # the loop stopped (IURS's weights at their floor after max_steps); success needs the
    # stop rule met.
    result = RESULTS.where(
        carry.nonfinite,
        RESULTS.nonfinite,
        RESULTS.where(
            solver_result != RESULTS.successful,
            solver_result,
            RESULTS.where(carry.stopped, RESULTS.successful, RESULTS.max_steps_reached),
        ),
    )
    metrics = dict(metrics, lam=jnp.asarray(lam, dtype=carry.energy.dtype))
    # A converged fit is "successful" only if it also reads inside from outside where its
    # targets say so; random normals converge to a fit that does not.
    metrics["offset_sign_disagreement"] = disagreement
    result = RESULTS.where(
        (result == RESULTS.successful) & (disagreement > MAX_OFFSET_SIGN_DISAGREEMENT),
        RESULTS.inconsistent_normals,
        result,
    )
    if throw:
        bad, which = unusable(result)
        fitted = eqx.branched_error_if(
            fitted, bad, which, [error_message(name) for name in RAISED_RESULTS]
        )
    stats = {"num_steps": carry.step, "energy_history": carry.history}
    return Solution(spline=fitted, metrics=metrics, stats=stats, result=result, state=carry.state)


@full_precision
def solve(
    solver: AbstractSolver,
    problem: Problem,
    spline: ImplicitSpline | None = None,
    *,
    throw: bool = True,
) -> Solution:
    """Run ``solver`` on ``problem`` from ``spline`` (default: C = 0, w = 1, as Algorithm 1).

    The loop is a ``jax.lax.while_loop``: it stops when ``|E_new - E_old| < solver.tol``
    (eq. 38), when the solver's ``terminate`` says so, after ``solver.max_steps`` steps,
    or when the energy is NaN/Inf. A non-finite step is not accepted: the solution keeps the
    last finite iterate. ``throw=True`` raises ``equinox.EquinoxRuntimeError`` on every
    verdict that is not a reconstruction (failed, nonfinite, inconsistent_normals,
    weights_at_floor, weights_at_ceiling), never on ``max_steps_reached`` (Algorithm 1
    stops there by design);
    ``throw=False`` only reports it in ``sol.result``. Traceable (jit, grad, vmap).

    ``throw=True`` compiles a host callback into the solve, which JAX's persistent
    compilation cache does not store: under your own ``jax.jit``, pass ``throw=False``
    and check ``sol.result`` if new processes should load the solve from that cache
    ([`jurs.fit`][] at top level does so by itself).

    It is ``start``, ``advance`` by ``solver.max_steps`` and ``finish``, one
    after the other, compiled as one program for each problem size, solver type and
    ``throw``: the solver's float settings enter it as arrays, so a new value compiles
    nothing.
    """
    # Python floats as arrays of the problem's dtype (as jurs.fit passes them): traced,
    # not static, and promoting no float32 problem to float64. Outside a jit the loop's
    # pieces would otherwise each compile op by op on a first call, many times the
    # solve's own time.
    solver = as_arrays(solver, problem.samples.dtype)
    return _compiled_solve(solver, problem, spline, throw)


@eqx.filter_jit
def _compiled_solve(solver, problem, spline, throw: bool) -> Solution:
    carry = start(solver, problem, spline)
    carry = advance(solver, problem, carry, solver.max_steps)
    return finish(solver, problem, carry, throw)
