"""``jurs.fit`` of a cloud held by several processes (``jax.distributed``): each process
lays out its own rows, and the one jitted solve runs over all devices (docs/sharding.md)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._problem.validate import normalise_grid
from .._solution.solution import RAISED_RESULTS, error_message
from .call import as_arrays, check_start, solve_fit
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
):
    """[`jurs.fit`][] of points and normals held by several processes (global
    ``jax.Array`` s split along the point axis, ``jurs._fit.sharding.spans_processes``);
    every process calls it with the same settings. The sample layout is built per process
    (``jurs._fit.sharding.process_problem``), the solve is the one jitted function over
    all devices, and the fitted spline is replicated on every device. What reads the whole
    cloud on a host is not run: the automatic settings (ValueError unless ``grid``,
    ``offset``, ``eps``, ``domain`` and ``solver`` are given), the estimation of normals,
    the orientation and doubt checks, the padding to stable sizes and the store of
    exported fits (docs/sharding.md)."""
    if normals is None:
        raise ValueError(
            "normals=None estimates normals from the whole cloud, which no process holds "
            "here: estimate them per process (jurs.estimate_normals) and pass them split "
            "like the points"
        )
    given = dict(grid=grid, offset=offset, eps=eps, domain=domain, solver=solver)
    missing = [name for name in PROCESS_SETTINGS if given[name] is None]
    if missing or smoothing is not None:
        raise ValueError(
            "points split over several processes: the automatic settings read the whole "
            "cloud, which no process holds; pass "
            + (", ".join(missing) if missing else "a solver with its lam, not smoothing")
            + " explicitly (a fit over several processes needs all of "
            + f"{', '.join(PROCESS_SETTINGS)}), "
            "e.g. from jurs.auto_settings(points, normals) on a subsample in one process, "
            "solver=jurs.LeastSquares(lam=settings.lam)"
        )
    if mask is not None:
        raise ValueError("mask: fits over several processes take no mask (docs/sharding.md)")
    for name, x in (("points", points), ("normals", normals)):
        if not isinstance(x, jax.Array) or x.is_fully_addressable or x.ndim != 2:
            raise ValueError(
                f"{name}: over several processes pass points and normals both as global "
                "(m, d) jax.Arrays split the same way along the point axis "
                "(jax.make_array_from_process_local_data)"
            )
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
    if top_level and throw and sol.status in RAISED_RESULTS:
        raise eqx.EquinoxRuntimeError(error_message(sol.status))
    return sol
