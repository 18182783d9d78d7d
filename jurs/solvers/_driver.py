"""The one loop every solver runs in."""

from __future__ import annotations

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp

from .._model.precision import full_precision
from .._model.spline import ImplicitSpline
from .._problem.energy import metrics as compute_metrics
from .._problem.problem import Problem
from .._solution.solution import RAISED_RESULTS, RESULTS, Solution, error_message, unusable
from .._solution.verdicts import MAX_OFFSET_SIGN_DISAGREEMENT, offset_sign_disagreement
from ._base import AbstractSolver


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
    (eq. 38), when the solver's :meth:`terminate` says so, after ``solver.max_steps`` steps,
    or when the energy is NaN/Inf. A non-finite step is not accepted: the solution keeps the
    last finite iterate. ``throw=True`` raises ``equinox.EquinoxRuntimeError`` on every
    verdict that is not a reconstruction (failed, nonfinite, inconsistent_normals,
    weights_at_floor), never on ``max_steps_reached`` (Algorithm 1 stops there by design);
    ``throw=False`` only reports it in ``sol.result``. Traceable (jit, grad, vmap).

    ``throw=True`` compiles a host callback into the solve, which JAX's persistent
    compilation cache does not store: under your own ``jax.jit``, pass ``throw=False``
    and check ``sol.result`` if new processes should load the solve from that cache
    (:func:`jurs.fit` at top level does so by itself).
    """
    if spline is None:
        dtype = problem.samples.dtype
        spline = ImplicitSpline(
            jnp.zeros(problem.shape, dtype),
            jnp.ones(problem.shape, dtype),
            problem.lower,
            problem.upper,
        )
    max_steps = solver.max_steps
    state, energy = solver.init(problem, spline)
    history = jnp.full((max_steps + 1,), jnp.nan, dtype=energy.dtype).at[0].set(energy)
    done, _ = solver.terminate(problem, state)

    def cond(carry):
        k, _, _, _, _, stop = carry
        return (k < max_steps) & ~stop

    def body(carry):
        k, state, energy, _, history, _ = carry
        new_state, new_energy = solver.step(problem, state)
        finite = jnp.isfinite(new_energy)
        # Keep the last finite iterate so a diverging run loses nothing.
        state = jax.tree_util.tree_map(
            lambda new, old: jnp.where(finite, new, old), new_state, state
        )
        converged = jnp.abs(new_energy - energy) < solver.tol
        stop_now, _ = solver.terminate(problem, state)
        history = history.at[k + 1].set(new_energy)
        stop = ~finite | converged | stop_now
        energy = jnp.where(finite, new_energy, energy)
        return k + 1, state, energy, ~finite, history, stop

    init = (
        jnp.array(0),
        state,
        energy,
        ~jnp.isfinite(energy),
        history,
        done | ~jnp.isfinite(energy),
    )
    # A checkpointed loop runs as a plain while loop forward and, unlike lax.while_loop,
    # can be reverse-differentiated (jax.grad of a loss of the fit), with O(log) memory.
    # The history buffer is written in place.
    k, state, energy, nonfinite, history, stop = eqxi.while_loop(
        cond, body, init, max_steps=max(max_steps, 1), kind="checkpointed", buffers=lambda c: c[4]
    )
    _, solver_result = solver.terminate(problem, state)
    # The solver's own verdict on its state, when it is not success, stands whether or not
    # the loop stopped (IURS's weights at their floor after max_steps); success needs the
    # stop rule met.
    result = RESULTS.where(
        nonfinite,
        RESULTS.nonfinite,
        RESULTS.where(
            solver_result != RESULTS.successful,
            solver_result,
            RESULTS.where(stop, RESULTS.successful, RESULTS.max_steps_reached),
        ),
    )
    fitted = solver.to_spline(problem, state)
    lam = solver.fitted_lam(state)
    metrics = compute_metrics(problem, fitted, lam)
    metrics["lam"] = jnp.asarray(lam, dtype=energy.dtype)
    # A converged fit is "successful" only if it also reads inside from outside where its
    # targets say so; random normals converge to a fit that does not.
    disagreement = offset_sign_disagreement(problem, fitted)
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
    stats = {"num_steps": k, "energy_history": history}
    return Solution(spline=fitted, metrics=metrics, stats=stats, result=result, state=state)
