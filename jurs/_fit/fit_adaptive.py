"""[`jurs.fit_adaptive`][]: the fit on a THB hierarchy, in one process or sharded over
several devices or processes. Its layout and host solves are ``adaptive.py``'s (with the
reasoning), the sharded ones ``adaptive_sharding.py``'s; this module chooses between them.
"""

from __future__ import annotations

from typing import cast

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from .._cloud.cloud import Cloud
from .._model.adaptive import AdaptiveSpline
from .._model.precision import on_device
from .._problem.adaptive import assemble_adaptive_problem, assembled_metrics
from .._solution.solution import (
    RESULTS,
    Solution,
    raise_unless_reconstruction,
)
from .._solution.verdicts import judge, judged_points
from ..solvers import AbstractSolver, LeastSquares, RobustLeastSquares
from .adaptive import (
    DEFAULT_RTOL,
    DIRECT_RTOL,
    FLOAT32_RTOL,
    METHODS,
    check_hierarchy_solver,
    exact_solve,
    hierarchy_layout,
    solve_on_hierarchy,
)
from .adaptive_sharding import fit_adaptive_across_processes, solve_sharded
from .settings import Settings, auto_settings, scale_free_lam
from .sharding import input_sharding, spans_processes


def fit_adaptive(
    points: Float[ArrayLike, "m d"] | Cloud,
    normals: Float[ArrayLike, "m d"] | None = None,
    *,
    finest: int | None = None,
    band: int | None = None,
    offset: float | None = None,
    eps: float | None = None,
    domain=None,
    smoothing: float | None = None,
    lam: float | None = None,
    rtol: float | None = None,
    max_steps: int = 10_000,
    settings: Settings | None = None,
    method: str | None = None,
    dtype=None,
    checks: bool = True,
    throw: bool = True,
    solver: AbstractSolver | None = None,
) -> Solution:
    """Fit an implicit spline on an adaptive (THB) basis: fine cells in a band around the
    data, coarse ones elsewhere, so that the cost grows with the shape's boundary rather
    than with its box.

    Args:
        points, normals: ``(m, 2)`` or ``(m, 3)``; normals outward (estimated with
            [`jurs.estimate_normals`][] when None). Or a ``jurs.Cloud`` with its normals
            (then ``normals`` is None), checked and measured once for all its fits.
        finest: cells of the finest level along the box's longest side; None chooses the
            cell from the data, ``max(s, 4 sigma)`` (``3 s`` on a surface;
            ``CELL_SPACINGS``), at most ``MAX_FINEST`` cells.
        band: cells of each level kept fine around the cells that hold samples (at least
            1); None takes ``DEFAULT_BAND``: 1 on a curve, 2 on a surface.
        offset, eps, domain, smoothing: as in [`jurs.auto_settings`][]; chosen from the
            data when None. ``lam`` overrides the lambda made from ``smoothing``.
        rtol, max_steps: the conjugate gradients' stop rule; ``rtol`` None takes
            ``DEFAULT_RTOL`` in float64 and ``FLOAT32_RTOL`` in float32 (a residual of
            1e-10 is below float32's rounding, and CG would run to ``max_steps``).
        method: ``"direct"`` (a sparse factorisation on the host, QDLDL), ``"cg"``
            (conjugate gradients in JAX, the path that runs on a GPU), ``"host_cg"``
            (the same conjugate gradients run by SciPy on the host, faster on a CPU),
            ``"multigrid"`` (conjugate gradients in JAX preconditioned by a V-cycle over
            the hierarchy's nested spaces: 10-30 steps where Jacobi takes hundreds, each
            dearer; docs/multigrid.md, "The multilevel solve of the hierarchy") or
            ``"host_multigrid"`` (the same solve run by SciPy on the host);
            None takes ``"direct"`` for a curve; for a surface, whose factor fills in
            (3D nested dissection fill grows as n^(4/3)), ``"host_cg"`` where JAX's
            default device is a CPU and the points are not sharded, ``"cg"`` otherwise.
        dtype: of the fit's arrays; None takes JAX's default float (float64 with
            ``jax_enable_x64``). A direct solve factorises in float64 on the host either
            way.
        settings: the [`jurs.Settings`][] to take offset, eps, domain and smoothing from
            (skips the measurement). The points it sets aside (``settings.set_aside``:
            points that stand alone) are left out of the fit, as [`jurs.fit`][] leaves
            them out.
        checks: judge the fit against its cloud on the host, as [`jurs.fit`][] judges
            its automatic fits: the orientation of the normals (``inconsistent_normals``)
            and the doubts (``doubtful``: parts cut or bridged, points far from the zero
            set, closed components away from the data; the reasons in
            ``sol.stats["doubts"]``). False skips them.
        throw: raise ``equinox.EquinoxRuntimeError`` when the verdict says the fit is not a
            reconstruction (``nonfinite``, ``inconsistent_normals``; never for
            ``max_steps_reached`` or ``doubtful``), as [`jurs.fit`][] does.
        solver: None (the exact solve with ``lam``), [`jurs.LeastSquares`][] (the same,
            with its ``lam``) or [`jurs.RobustLeastSquares`][] (its reweighted solves:
            outliers weighed down, ``sol.state.point_weights`` one per point fitted, in the
            cloud's order without the points ``settings`` set aside). A solver keeps its
            own ``lam``, the weight of the hierarchy's ``R`` (pass no ``lam`` beside it).
            Other solvers run on the uniform grid only and are refused with the reason.
            A robust fit runs in one process, on points not sharded.

    Returns:
        A [`jurs.Solution`][] whose ``spline`` is a [`jurs.AdaptiveSpline`][];
        ``sol.stats`` holds ``num_steps`` (CG steps), ``residual``, ``levels``,
        ``active`` (functions per level) and ``finest`` (cells per axis of the finest
        level over the box). ``result`` is ``successful``, ``max_steps_reached`` (CG
        stopped first) or ``nonfinite``, or with ``checks`` the verdicts above.

    Points (and normals) sharded along the point axis over several devices, or split over
    several processes (``jax.distributed``), fit where they lie
    (``jurs._fit.adaptive_sharding``, docs/sharding.md "Adaptive fits"): CG splits the
    samples' rows over the devices and reduces only active-function-sized sums; a direct
    solve reads every shard on the host (one process), or factorises the processes'
    summed normal equations in each (over processes, where the settings are chosen over
    every process's points and the host checks are not run). ``sol.stats["devices"]``
    counts the devices.

    Differentiable: with the structure fixed (the same points' leaves), ``jax.grad``
    through [`jurs.internal.make_adaptive_problem`][] and the solve is exact (the solve
    sits behind ``lax.custom_linear_solve``).
    """
    if method is not None and method not in METHODS:
        raise ValueError(
            f"method must be one of {', '.join(map(repr, METHODS))} or None, got {method!r}"
        )
    if band is not None and band < 1:
        raise ValueError(f"band must be at least 1 cell, got {band}")
    check_hierarchy_solver(solver)
    if solver is not None:
        if lam is not None:
            raise ValueError("pass lam or a solver, not both: a solver keeps its own lam")
        if isinstance(solver, RobustLeastSquares) and (
            spans_processes(points, normals) or input_sharding(points, normals) is not None
        ):
            raise ValueError(
                "a robust fit on the hierarchy runs in one process on points that are not "
                "sharded; gather them first, or fit with jurs.LeastSquares"
            )
        lam = float(solver.lam)
    if spans_processes(points, normals):  # each process assembles its own samples' rows
        return fit_adaptive_across_processes(
            points, normals, finest=finest, band=band, offset=offset, eps=eps, domain=domain,
            smoothing=smoothing, lam=lam, rtol=rtol, max_steps=max_steps, settings=settings,
            method=method, dtype=dtype, throw=throw,
        )  # fmt: skip
    if isinstance(points, Cloud):
        if normals is not None or points.normals is None or points.mask is not None:
            raise ValueError(
                "fit_adaptive(cloud): pass a jurs.Cloud with its normals and no mask, "
                "and no normals beside it"
            )
        cloud = points
    else:
        if normals is None:
            from .._cloud.normals import estimate_normals

            normals = cast(np.ndarray, estimate_normals(points))
        # Checked once (NaN, shapes, zero normals, degenerate clouds) and exact repeats
        # merged, whether or not the settings are given.
        cloud = Cloud(points, normals)
    if settings is None:
        settings = auto_settings(cloud, offset=offset, eps=eps, domain=domain)
    keep = judged_points(cloud, settings)  # the cloud has no mask: all but those set aside
    points_np = cloud.points[keep]
    normals_np = np.asarray(cloud.normals, float)[keep]
    ndim = points_np.shape[1]
    # Points sharded over devices (one process): CG keeps each device's samples there.
    sharding = input_sharding(cloud.given_points, cloud.given_normals)
    if method is None:
        on_cpu = sharding is None and jax.default_backend() == "cpu"
        method = "direct" if ndim == 2 else "host_cg" if on_cpu else "cg"
    layout = hierarchy_layout(settings, ndim, finest, band, offset, eps, dtype)
    lower, upper, dtype = layout["lower"], layout["upper"], layout["dtype"]
    problem, matrices = assemble_adaptive_problem(points_np, normals_np, **layout)
    hierarchy = problem.hierarchy
    finest_level = hierarchy.num_levels - 1
    finest_cell = float(np.max((upper - lower) / np.asarray(hierarchy.cells(finest_level))))
    if lam is None:
        strength = settings.smoothing if smoothing is None else float(smoothing)
        diagonal = float(np.linalg.norm(points_np.max(0) - points_np.min(0)))
        lam = scale_free_lam(strength, 3 * len(points_np), diagonal, lower, upper, finest_cell)
    if rtol is None:
        rtol = DEFAULT_RTOL if dtype == jnp.float64 else FLOAT32_RTOL
    state, settled = None, True
    if method == "cg" and sharding is not None:
        control_np, steps, residual, metrics = solve_sharded(
            problem, matrices, float(lam), float(rtol), int(max_steps), dtype, sharding
        )
        control = on_device(control_np, dtype)
        tolerance = rtol
    else:  # a factorisation, or CG on the assembled matrices (SciPy, or JAX compiled)
        # host_cg reads every sample on the host, as a direct solve does.
        solve = exact_solve(
            method, problem, matrices, float(lam), float(rtol), int(max_steps), dtype
        )
        control_np, steps, residual, state, settled = solve_on_hierarchy(
            LeastSquares(lam=float(lam)) if solver is None else solver, problem, matrices, solve
        )
        control = on_device(control_np, dtype)
        metrics = assembled_metrics(problem, matrices, control_np, float(lam))
        # A direct solve is exact up to rounding; a residual far above it means the
        # factorisation met a (numerically) singular matrix.
        tolerance = max(rtol, DIRECT_RTOL) if method == "direct" else rtol
    spline = AdaptiveSpline(hierarchy, control, on_device(np.ones(control.shape), dtype))
    finite = bool(np.all(np.isfinite(np.asarray(control))))
    converged = float(residual) <= tolerance and settled
    result = (
        RESULTS.successful
        if finite and converged
        else RESULTS.max_steps_reached
        if finite
        else RESULTS.nonfinite
    )
    stats = {
        "method": method,
        "num_steps": int(steps),
        "residual": float(residual),
        "levels": hierarchy.num_levels,
        "active": hierarchy.active_counts,
        "finest": hierarchy.cells(finest_level),
    }
    if sharding is not None:  # the devices the solve ran over (a direct solve: the host)
        stats["devices"] = len(sharding.device_set) if method == "cg" else 1
    sol = Solution(spline, metrics, stats, result, state, settings)
    if checks:
        sol = judge(sol, cloud, settings, layout["offset"])
    raise_unless_reconstruction(sol, throw)
    return sol
