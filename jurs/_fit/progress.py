"""Running an iterative fit in chunks of steps: progress reports and iteration snapshots.

``jurs.fit`` runs a whole solve in one compiled loop. To report progress, or to look at the
iterate after given step counts (the paper's Fig. 15), :func:`fit_in_chunks` runs the same
solver ``chunk`` steps at a time, warm-starting each call from the previous spline. For
I-PIA and IURS the state is a function of the spline (C, w) alone, so the chunked run
follows the same iterates as one run (to rounding; the tests check this). Other solvers are
run in one call.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._model.spline import ImplicitSpline
from .._problem.problem import make_problem
from .._solution.solution import RAISED_RESULTS, RESULTS, Solution, error_message
from ..solvers import IPIA, IURS, AbstractSolver
from .fit import fit
from .settings import auto_settings

#: Solvers whose warm start from a spline continues the same run.
CHUNKABLE = (IPIA, IURS)


def chunk_size(steps: int, target_chunks: int = 25) -> int:
    """A divisor of ``steps`` near ``steps / target_chunks`` (one compile for all chunks);
    ``steps`` itself when none is reasonably close."""
    if steps <= target_chunks:
        return max(steps, 1)
    ideal = steps / target_chunks
    divisors = [c for c in range(1, steps + 1) if steps % c == 0 and ideal / 4 <= c <= ideal * 4]
    return min(divisors, key=lambda c: abs(np.log(c / ideal))) if divisors else steps


def fit_in_chunks(
    points,
    normals,
    *,
    solver: AbstractSolver,
    chunk: int | None = None,
    checkpoints=(),
    callback: Callable[[int, int], None] | None = None,
    **fit_kwargs,
):
    """Run ``jurs.fit`` with ``solver`` in chunks of ``chunk`` steps.

    Args:
        solver: the solver; its ``max_steps`` is the total number of steps.
        chunk: steps per call (default :func:`chunk_size`, or the gcd with the checkpoints).
        checkpoints: step counts at which to keep the spline (e.g. ``(0, 10, 50, 200)``).
        callback: called as ``callback(steps_done, max_steps)`` after every chunk.
        **fit_kwargs: passed to :func:`jurs.fit` (grid, offset, eps, domain, ...);
            ``throw`` (default True) applies to the whole run's final verdict.

    Returns:
        ``(solution, snapshots)``: the final :class:`jurs.Solution`, with ``num_steps`` and
        ``energy_history`` of the whole run, and a dict ``{step: spline}`` for the
        checkpoints reached (a run that converges early stops there).
    """
    total = int(solver.max_steps)
    checkpoints = sorted({int(c) for c in checkpoints})
    if any(c < 0 or c > total for c in checkpoints):
        raise ValueError(f"checkpoints must lie in [0, max_steps = {total}], got {checkpoints}")
    if not isinstance(solver, CHUNKABLE):
        if any(c != total for c in checkpoints):
            raise ValueError(
                f"{type(solver).__name__} runs in one call: the only checkpoint "
                f"it can give is max_steps = {total}"
            )
        sol = fit(points, normals, solver=solver, **fit_kwargs)
        if callback:
            callback(total, total)
        return sol, {c: sol.spline for c in checkpoints}
    if chunk is None:
        chunk = chunk_size(total)
        for c in checkpoints:
            chunk = int(np.gcd(chunk, c)) if c else chunk
    chunk = max(1, int(chunk))
    snapshots = {}
    settings, init = _fixed_settings_and_start(points, normals, fit_kwargs)
    # Every chunk is fitted with throw=False: a verdict on the iterate so far is not the
    # run's; the run's own verdict is raised at the end.
    throw = fit_kwargs.pop("throw", True)
    history = []
    done, sol = 0, None
    start = init
    while done < total:
        n = min(chunk, total - done)
        sol = fit(
            points,
            normals,
            solver=dataclasses.replace(solver, max_steps=n),
            init=init,
            throw=False,
            **fit_kwargs,
        )
        k = int(sol.stats["num_steps"])
        h = np.asarray(sol.stats["energy_history"])
        history.append(h[: k + 1] if not history else h[1 : k + 1])
        done += k
        if 0 in checkpoints and 0 not in snapshots:
            snapshots[0] = start
        init = sol.spline
        if done in checkpoints:
            snapshots[done] = sol.spline
        if callback:
            callback(done, total)
        # A chunk that ran all its steps goes on, also where the host-side checks gave a
        # verdict on the iterate so far (normals, weights): a single fit would have gone on.
        ran_on = (RESULTS.max_steps_reached, RESULTS.inconsistent_normals, RESULTS.weights_at_floor)
        if k < n or not any(bool(sol.result == r) for r in ran_on):
            break  # converged, diverged or stopped by the solver
    if sol is None:  # max_steps = 0
        sol = fit(points, normals, solver=solver, init=init, throw=False, **fit_kwargs)
        history.append(np.asarray(sol.stats["energy_history"]))
        if 0 in checkpoints:
            snapshots[0] = sol.spline
    full = np.full(total + 1, np.nan)
    h = np.concatenate(history)
    full[: len(h)] = h
    stats = dict(sol.stats, num_steps=np.asarray(done), energy_history=full)
    if throw and sol.status in RAISED_RESULTS:
        raise eqx.EquinoxRuntimeError(error_message(sol.status))
    return Solution(sol.spline, sol.metrics, stats, sol.result, sol.state, settings), snapshots


def _fixed_settings_and_start(points, normals, fit_kwargs):
    """``(settings, init)``: the automatic settings chosen once (None where grid, offset
    and eps are given), written into ``fit_kwargs``, and the start popped from it (or
    made), so that every chunk fits the same problem."""
    settings = None
    if any(fit_kwargs.get(k) is None for k in ("grid", "offset", "eps")):
        # Choose once, so every chunk fits the same problem.
        keys = ("grid", "offset", "eps", "domain", "margin")
        settings = auto_settings(
            points, normals, **{k: fit_kwargs[k] for k in keys if fit_kwargs.get(k) is not None}
        )
        fit_kwargs.update(grid=settings.grid, offset=settings.offset, eps=settings.eps)
    init = fit_kwargs.pop("init", None)
    if init is None:
        # An explicit start (C = 0, w = 1, as the solvers' default) so every chunk has the
        # same argument structure and the fit compiles once.
        keys = ("offset", "eps", "domain", "margin", "mask")
        problem = make_problem(
            points,
            normals,
            grid=fit_kwargs["grid"],
            **{k: fit_kwargs[k] for k in keys if k in fit_kwargs},
        )
        init = ImplicitSpline(
            jnp.zeros(problem.shape, problem.lower.dtype),
            jnp.ones(problem.shape, problem.lower.dtype),
            problem.lower,
            problem.upper,
        )
    return settings, init
