"""``jurs.fit`` of a cloud held by several processes (``jax.distributed``): each process
lays out its own rows, and the one jitted solve runs over all devices (docs/sharding.md)."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from .._cloud.parts import spans_processes
from .._jit import as_arrays
from .._problem.validate import normalise_grid
from .._solution.solution import raise_unless_reconstruction
from ..solvers import LeastSquares
from .adaptive import auto_finest, solver_lam
from .adaptive_sharding import fit_adaptive_across_processes
from .call import check_start, solve_fit
from .process_settings import check_global_arrays, settings_across_processes
from .sharding import (
    PROCESS_SETTINGS,
    input_sharding,
    process_problem,
    replicate_across_processes,
)


def fit_across_processes(
    points,
    normals,
    grid,
    solver,
    offset,
    eps,
    domain,
    margin,
    init,
    mask,
    bucket_size,
    smoothing,
    throw,
    basis="auto",
):
    """[`jurs.fit`][] of points and normals held by several processes (global
    ``jax.Array`` s split along the point axis, ``jurs._fit.sharding.spans_processes``);
    every process calls it with the same settings. The sample layout is built per process
    (``jurs._fit.sharding.process_problem``), the solve is the one jitted function over
    all devices, and the fitted spline is replicated on every device. Settings not given
    are chosen by ``jurs._fit.process_settings.settings_across_processes`` (the default
    solver: ``jurs.LeastSquares`` with its lambda; points standing alone are not set
    aside) and returned in ``sol.settings``; normals None are estimated by
    ``jurs._cloud.normals.normals_across_processes``. What reads the whole cloud on a host is not
    run: the orientation and doubt checks, the padding to
    stable sizes and the store of exported fits (docs/sharding.md). ``basis="adaptive"``:
    [`jurs.fit_adaptive`][]'s fit over the processes with the settings chosen here
    (``jurs._fit.adaptive_sharding.fit_adaptive_across_processes``)."""
    if normals is None:  # estimated over all processes' points, split like them
        if not spans_processes(points):
            raise ValueError("normals: pass them split like the points, or None")
        # SciPy's graphs and KD-trees: loaded when first needed, not on import jurs.
        from .._cloud.normals import normals_across_processes

        normals = normals_across_processes(points)
    if smoothing is not None and solver is not None:
        raise ValueError(
            "smoothing sets the default solver's lambda; with a solver given, set its lam instead"
        )
    check_global_arrays(points, normals)
    if mask is not None:
        raise ValueError("mask: fits over several processes take no mask (docs/sharding.md)")
    if basis == "adaptive":  # the arguments only the grid takes were refused by jurs.fit
        settings = settings_across_processes(
            points, normals, None, offset, eps, domain, margin, smoothing
        )
        lam = solver_lam(solver, None, points, normals)  # refuses a robust solver here
        return fit_adaptive_across_processes(
            points, normals, finest=auto_finest(settings), lam=lam, settings=settings, throw=throw
        )
    given = dict(grid=grid, offset=offset, eps=eps, domain=domain, solver=solver)
    settings = None
    if any(given[name] is None for name in PROCESS_SETTINGS):
        shape = None if grid is None else normalise_grid(grid, int(points.shape[1]))
        settings = settings_across_processes(
            points, normals, shape, offset, eps, domain, margin, smoothing, solver
        )
        grid, offset, eps, domain = settings.grid, settings.offset, settings.eps, settings.domain
        solver = LeastSquares(lam=settings.lam) if solver is None else solver
    shape = normalise_grid(grid, int(points.shape[1]))
    check_start(shape, solver, init)  # memory: per process, by process_problem
    dtype = jnp.result_type(float)
    problem = process_problem(
        points, normals, shape, offset, eps, domain, margin, bucket_size, dtype, solver
    )
    sharding = input_sharding(points, normals)
    assert sharding is not None
    solver = replicate_across_processes(as_arrays(solver, dtype), sharding)
    init = replicate_across_processes(init, sharding)
    sol, top_level = solve_fit(problem, solver, init, throw)
    if top_level:
        raise_unless_reconstruction(sol, throw)
    if settings is not None:
        sol = dataclasses.replace(sol, settings=settings)
    return sol
