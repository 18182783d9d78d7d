"""The one loop every solver runs in."""

from __future__ import annotations

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp

from .._model.precision import full_precision
from .._model.spline import ImplicitSpline
from .._problem.energy import layout_residuals
from .._problem.energy import metrics as compute_metrics
from .._problem.problem import Problem, values_by_point
from .._solution.solution import RAISED_RESULTS, RESULTS, Solution, error_message, unusable
from ._base import AbstractSolver

#: A fit whose stop rule was met but whose own sign is wrong at more than this fraction of
#: the offset samples (g <= 0 outside, g >= 0 inside) is reported as
#: ``RESULTS.inconsistent_normals``. Measured with the automatic settings: clean and noisy
#: clouds 0-2 %, 10 % positional outliers 12.5 %, random normals 32 %, every other normal
#: flipped 42 %.
MAX_OFFSET_SIGN_DISAGREEMENT = 0.2
#: The check reads every k-th point, at most this many: its per-point sums are arrays of
#: the points' length, which a sharded fit all-reduces to every device (a 1e7-point cloud:
#: 240 MB a device, more than its share of the samples on 8 devices). 65536 points estimate
#: the fraction within about 0.4 % (two standard errors at the threshold).
SIGN_CHECK_POINTS = 1 << 16


def offset_sign_disagreement(problem: Problem, spline: ImplicitSpline):
    """Fraction of the points whose two offset samples the fit reads the wrong way round:
    ``g(P + d n) <= g(P - d n)``, the fit rising inward across the point.

    The two samples are compared with each other, not with 0: where the grid's cells are
    much wider than d (a dense cloud on a capped grid) the zero set lies farther than d
    from the data, so an offset can sit on the wrong side of it while the fit still
    rises outward through the point (1e6 points of a circle: a third of the offsets on the
    wrong side of an accurate fit). Above :data:`SIGN_CHECK_POINTS` points, an evenly
    strided subset of them is read."""
    local = problem.local
    mask, targets = local.to_layout(problem.mask), local.to_layout(problem.targets)
    r, _, _ = layout_residuals(local, mask, targets, spline.control, spline.weights)
    m = problem.num_points
    # (The table form, for small problems only, carries it as floats: exact there.)
    index = local.to_layout(problem.sample_index).astype(jnp.int32)
    stride = -(-m // SIGN_CHECK_POINTS)  # every point up to SIGN_CHECK_POINTS
    size = -(-m // stride)
    point, kind = index % m, index // m
    real = (mask > 0) & (point % stride == 0)
    index = kind * size + point // stride
    _, g_out, g_in = values_by_point(r + targets, index, real, size)  # r = g - b where real
    counted = values_by_point(jnp.ones_like(r), index, real, size)[1] > 0
    wrong = counted & (g_out <= g_in)
    return jnp.sum(wrong) / jnp.maximum(jnp.sum(counted), 1)


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
