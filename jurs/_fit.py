"""``jurs.fit``: points and normals in, a fitted implicit spline out."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp

from ._compile import COMPILER_OPTIONS
from ._defaults import auto_settings
from ._problem import DEFAULT_MARGIN, _is_concrete, make_problem, normalise_grid
from ._solution import RESULTS, Solution
from ._spline import ImplicitSpline
from .solvers import AbstractSolver, LeastSquares, solve


def _as_arrays(tree, dtype):
    """Python floats -> 0-d arrays, so new hyperparameter values do not recompile."""
    return jax.tree_util.tree_map(
        lambda x: jnp.asarray(x, dtype) if isinstance(x, float) else x, tree
    )


def _run(problem, solver, init, throw):
    return solve(solver, problem, init, throw=throw)


_solve = eqx.filter_jit(_run)
# The same compiled with COMPILER_OPTIONS, for large problems at top level (see fit).
_solve_reassociating = eqx.filter_jit(_run, compiler_options=COMPILER_OPTIONS)


def _at_top_level(tree) -> bool:
    """Whether no JAX transformation is tracing, nor holds a leaf of ``tree``: XLA takes
    compiler options only on an outermost jit."""
    if not _is_concrete(tree):
        return False
    try:
        from jax._src.core import trace_state_clean  # private: without it, never
    except ImportError:
        return False
    return bool(trace_state_clean())


def _reassociation_pays(problem, solver) -> bool:
    """For solvers that declare themselves safe with :data:`jurs.COMPILER_OPTIONS`
    (``reassociation_safe``) on problems in the bucketed power form (the large ones, where
    the per-bucket sums are and where the options were measured to pay)."""
    local = problem.local
    return type(solver).reassociation_safe and local.terms is None and local.bucket_size > 1


def reassociates(problem, solver, init=None) -> bool:
    """Whether :func:`jurs.fit` compiles this solve with :data:`jurs.COMPILER_OPTIONS`:
    where they pay (:func:`_reassociation_pays`), when called at top level."""
    return _reassociation_pays(problem, solver) and _at_top_level((problem, solver, init))


def fit(
    points,
    normals,
    *,
    grid=None,
    solver: AbstractSolver | None = None,
    offset=None,
    eps=None,
    domain=None,
    margin: float = DEFAULT_MARGIN,
    init: ImplicitSpline | None = None,
    mask=None,
    bucket_size: int | None = None,
    smoothing: float | None = None,
    throw: bool = True,
) -> Solution:
    """Fit an implicit spline whose zero set passes through ``points``.

    With nothing but points and normals, the grid, the offset d, eps and the solver are
    chosen from the data (:func:`jurs.auto_settings`: cells a few point spacings or noise
    widths wide, d from the spacing and noise, the exact solve :class:`jurs.LeastSquares`
    with a scale-free lambda); ``sol.settings`` records the choices. Give any of them to
    override; the paper's Example 1 settings are ``grid=(9, 9), offset=0.1, eps=0.01``.

    Args:
        points: ``(m, 2)`` data points.
        normals: ``(m, 2)`` outward normals (normalised here).
        grid: ``N`` or ``(N, M)`` basis functions along x and y (>= 4); None chooses.
        solver: any jurs solver; None: ``LeastSquares(lam=settings.lam)``, the regularised
            exact solve. A solver given keeps its own lambda.
        offset: d, distance of the offset samples (eq. 4); None chooses.
        eps: target value at the offsets (eq. 5); None takes ``eps = d``.
        domain: ``((x_min, y_min), (x_max, y_max))`` or None for the samples' bounding box
            plus ``margin`` x its longest side.
        init: starting spline on the same box and grid; default C = 0, w = 1.
        mask: optional ``(m,)`` booleans, False marking padding points that take no part
            (for ``jax.vmap`` over clouds padded to one size).
        bucket_size: sample layout, see :func:`jurs.make_problem` (None chooses).
        smoothing: the dimensionless strength of the default solver's lambda
            (:func:`jurs.auto_settings`); None chooses. Only with ``solver=None``: a solver
            given keeps its own lambda.
        throw: raise if the energy becomes NaN/Inf (the last finite iterate is kept either
            way; ``sol.result`` says what happened). Called outside any JAX
            transformation, the fit is checked once it has run, so this call then waits
            for it.

    Returns:
        :class:`jurs.Solution`. Jit-compiled inside; traceable, so ``jax.grad`` and
        ``jax.vmap`` go through it once ``grid``, ``offset``, ``eps`` and ``solver`` are
        given (automatic choices need concrete points; input checks run only on concrete
        inputs).

    Large problems (more than :data:`jurs._spline.TABLE_MAX_SLOTS` samples, or
    ``bucket_size > 1`` given) fitted by jurs's own solvers outside any JAX transformation
    are compiled with :data:`jurs.COMPILER_OPTIONS`, which vectorise their per-bucket sums
    (``benchmarks/results/speed.md`` times the IURS step at 1e6 points with and without
    them). The result then differs from the same fit under a caller's ``jit`` at rounding
    level.
    """
    settings = None
    if smoothing is not None and solver is not None:
        raise ValueError("smoothing sets the default solver's lambda; with a solver given, "
                         "set its lam instead")
    if grid is None or offset is None or eps is None or solver is None:
        if mask is not None:
            raise ValueError("automatic settings do not take a mask; pass grid, offset, eps "
                             "and solver explicitly for padded batches")
        settings = auto_settings(points, normals, grid=grid, offset=offset, eps=eps,
                                 domain=domain, margin=margin, smoothing=smoothing)
        grid, offset, eps = settings.grid, settings.offset, settings.eps
        solver = LeastSquares(lam=settings.lam) if solver is None else solver
    shape = normalise_grid(grid)
    if not isinstance(solver, AbstractSolver):
        raise TypeError(f"solver must be a jurs solver, got {type(solver).__name__}")
    dtype = jnp.result_type(float)
    if init is not None and tuple(init.shape) != shape:
        raise ValueError(f"init spline has grid {init.shape}, expected {shape}")
    # The problem is built outside the solver's jit: its sample layout is chosen on the
    # host from concrete data (see make_problem); under a caller's jit/grad/vmap it is traced.
    problem = make_problem(points, normals, grid=shape, offset=offset, eps=eps, domain=domain,
                           margin=margin, mask=mask, bucket_size=bucket_size, dtype=dtype)
    solver = _as_arrays(solver, dtype)
    top_level = _at_top_level((problem, solver, init))
    run = (_solve_reassociating if top_level and _reassociation_pays(problem, solver)
           else _solve)
    if top_level:
        # ``throw`` checked on the host after the call, not by a host callback inside it:
        # a compiled fit with a callback is never written to JAX's persistent compilation
        # cache, and without one a new process loads the fit instead of compiling it.
        sol = run(problem, solver, init, False)
        if throw and bool(sol.result == RESULTS.nonfinite):
            raise eqx.EquinoxRuntimeError(RESULTS[RESULTS.nonfinite])
    else:
        sol = run(problem, solver, init, throw)
    return sol if settings is None else dataclasses.replace(sol, settings=settings)
